// A succeeded reconstruction: its statistics, downloads, the 3D view of cameras and points, its figures.
import { api, blobUrl, download, getJson } from "../api.js";
import { h, section, showError } from "../dom.js";
import { reconstructionSummary } from "../format.js";
import { parsePly } from "../ply.js";
import { paths } from "../urls.js";
import { showReconstruction } from "../viewer.js";

const DOWNLOADS = ["points.ply", "colmap.zip", "transforms.json"];
const FIGURE_PREFIX = "figures/";

export function reconstructionPanel(page, jobId) {
  const stats = h("div"), view = h("div", { class: "view3d", id: "view3d" }), figures = h("div", { class: "grid figures" });
  const panel = h("div", { class: "panel", id: `reconstruction-${jobId}` }, h("h2", {}, "Reconstruction"), stats,
    view, h("h2", {}, "Figures"), figures);
  section(panel, async () => {
    const model = await getJson(paths.reconstruction(jobId));
    const downloads = DOWNLOADS.map((name) =>
      h("button", { class: "secondary", onclick: () => download(model.files[name], name).catch((e) => showError(e.message)) }, name));
    stats.replaceChildren(h("p", {}, reconstructionSummary(model),
      ...model.unregistered.map((u) => h("span", { class: "muted" }, `${u.image}: ${u.reason}. `))),
    h("p", {}, "Downloads: ", ...downloads));
    const ply = parsePly(await (await api(model.files["points.ply"])).arrayBuffer());
    page.disposers.push(showReconstruction(view, {
      points: ply, cameras: model.cameras, intrinsics: model.intrinsics,
      registrationOrder: model.statistics.registration_order || model.cameras.map((c) => c.image) }).dispose);
    for (const [name, url] of Object.entries(model.files).filter(([n]) => n.startsWith(FIGURE_PREFIX))) {
      figures.append(h("figure", {}, h("img", { src: await blobUrl(url), alt: name }),
        h("figcaption", {}, name.slice(FIGURE_PREFIX.length))));
    }
  });
  return panel;
}
