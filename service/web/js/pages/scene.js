// #/scenes/{id} : one scene's stages and log; each stage's panel once it has something to show.
import { blobUrl, getJson } from "../api.js";
import { h, poll, progressBar, section, stateText } from "../dom.js";
import { expectedTime, heldOutCaption, isActive, percent } from "../format.js";
import { actions } from "../panels/actions.js";
import { nerfPanel } from "../panels/nerf.js";
import { reconstructionPanel } from "../panels/reconstruction.js";
import { paths, routes } from "../urls.js";

export function scenePage(main, page, sceneId) {
  const head = h("div"), body = h("div");
  main.append(h("h1", {}, `Scene ${sceneId.slice(0, 8)}`), head, body);
  const shown = new Set();
  poll(page, async () => {
    const scene = await getJson(paths.scene(sceneId));
    head.replaceChildren(h("div", { class: "panel", id: "scene", dataset: { state: scene.state, stage: scene.stage } },
      h("p", {}, stateText(scene.state), ` — stage ${scene.stage} `, progressBar(scene.progress), ` ${percent(scene.progress)}`),
      scene.error ? h("p", { class: "error" }, scene.error) : null,
      scene.expected_seconds ? h("p", { class: "muted", id: "expected" }, expectedTime(scene.expected_seconds)) : null,
      h("table", {}, h("tbody", {}, scene.stages.map((s) => h("tr", {},
        h("td", {}, s.name), h("td", {}, stateText(s.state)), h("td", {}, progressBar(s.progress)),
        h("td", {}, s.job_ids.map((id) => h("a", { href: routes.job(id) }, `job ${id.slice(0, 8)} `))))))),
      h("pre", { class: "log" }, scene.log.join("\n")),
      actions("scene", sceneId, scene.state, () => { location.hash = routes.list; })));
    const [reconstruction, nerf, views] = scene.stages;
    if (reconstruction.state === "succeeded" && !shown.has("r")) {
      shown.add("r"); body.append(reconstructionPanel(page, reconstruction.job_ids.at(-1)));
    }
    if (nerf.job_ids.length && !shown.has(nerf.job_ids.at(-1))) {
      shown.add(nerf.job_ids.at(-1)); body.append(nerfPanel(page, nerf.job_ids.at(-1)));
    }
    if (views.state === "succeeded" && !shown.has("v")) {
      shown.add("v");
      const renders = h("div", { class: "grid renders", id: "held-out" });
      body.append(h("div", { class: "panel" }, h("h2", {}, "Held-out views, rendered"), renders));
      section(renders, async () => {
        for (const view of scene.held_out) {
          renders.append(h("figure", {}, h("img", { src: await blobUrl(view.url), alt: view.image }),
            h("figcaption", {}, heldOutCaption(view))));
        }
      });
    }
    return isActive(scene.state);
  });
}
