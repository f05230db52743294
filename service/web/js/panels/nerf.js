// A NeRF job: the training curve, the latest validation render, the interactive novel view, the orbit
// video and the checkpoints.
import { blobUrl, download, getJson, postJson } from "../api.js";
import { h, poll, showError } from "../dom.js";
import { checkpointTags, decibels, isActive, megabytes, trainingSummary } from "../format.js";
import { drawCurve } from "../psnr_plot.js";
import { paths } from "../urls.js";
import { novelView } from "./novel_view.js";

const VIDEO_REQUEST = { num_frames: 24, width: 160, height: 120 };

// The registered cameras of the reconstruction a NeRF trained on ([] for an uploaded dataset or when the
// reconstruction is gone: the novel view then orbits freely).
async function registeredCameras(job) {
  if (!job.source_job_id) return [];
  try {
    return (await getJson(paths.reconstruction(job.source_job_id))).cameras || [];
  } catch {
    return [];
  }
}

export function nerfPanel(page, jobId) {
  const canvas = h("canvas", { class: "plot", id: `psnr-${jobId}` });
  const summary = h("p", { class: "muted" }, "waiting for the first metrics…");
  const validation = h("div", { class: "renders" }), novel = h("div"), video = h("div"), checkpoints = h("tbody");
  let lastValidation = null, shownNovel = false;
  const videoButton = h("button", { class: "secondary", onclick: async () => {
    try {
      await postJson(paths.nerf(jobId, "video"), VIDEO_REQUEST);
      video.replaceChildren(h("p", { class: "muted" }, "rendering the orbit video…"));
      showVideo();
    } catch (error) { showError(error.message); }
  } }, "Render an orbit video");
  const showVideo = () => poll(page, async () => {
    try {
      video.replaceChildren(h("img", { src: await blobUrl(paths.nerf(jobId, "video")), alt: "orbit video", id: `video-${jobId}` }));
      return false;
    } catch (error) {
      // 404: none queued yet (a scene queues one when its NeRF is trained); 409: one is being rendered.
      if (/^GET \S+: 404/.test(error.message) || /: 409 .*(queued|running)/.test(error.message)) return true;
      video.replaceChildren(h("p", { class: "muted" }, error.message));
      return false;
    }
  });
  showVideo();
  poll(page, async () => {
    const nerf = await getJson(paths.nerf(jobId));
    drawCurve(canvas, nerf.metrics);
    summary.textContent = trainingSummary(nerf.job.state, nerf.metrics);
    const val = [...nerf.metrics].reverse().find((m) => m.val_psnr != null);
    if (val && val.step !== lastValidation) {
      lastValidation = val.step;
      validation.replaceChildren(h("img", { src: await blobUrl(paths.nerf(jobId, "validation")), alt: `validation render at step ${val.step}` }),
        h("p", { class: "muted" }, `step ${val.step}: ground truth | render | depth`));
    }
    const list = await getJson(paths.nerf(jobId, "checkpoints"));
    checkpoints.replaceChildren(...list.map((c) => h("tr", {}, h("td", {}, String(c.step)),
      h("td", {}, checkpointTags(c)), h("td", {}, c.val_psnr != null ? decibels(c.val_psnr) : ""),
      h("td", {}, megabytes(c.size_bytes)),
      h("td", {}, h("button", { class: "secondary", onclick: () => download(c.url, `step_${c.step}.pt`).catch((e) => showError(e.message)) }, "download")))));
    if (list.length && !shownNovel && nerf.config?.orbit) {
      shownNovel = true;
      novel.replaceChildren(novelView(jobId, nerf.config, await registeredCameras(nerf.job)));
    }
    return isActive(nerf.job.state) || !shownNovel && list.length > 0;
  });
  return h("div", { class: "panel", id: `nerf-${jobId}` }, h("h2", {}, "NeRF training"), summary, canvas,
    h("div", { class: "grid" },
      h("div", {}, h("h2", {}, "Latest validation render"), validation),
      h("div", {}, h("h2", {}, "Novel view"), novel),
      h("div", {}, h("h2", {}, "Orbit video"), videoButton, video)),
    h("h2", {}, "Checkpoints"),
    h("table", {}, h("thead", {}, h("tr", {}, ["Step", "", "Validation PSNR", "Size", ""].map((t) => h("th", {}, t)))), checkpoints));
}
