// The interactive novel view: drag the image to move the camera; each new camera is rendered by the service
// and shown as soon as it arrives (one request in flight, the latest position queued).
import { blobUrl } from "../api.js";
import { h } from "../dom.js";
import { createNovelCamera } from "../novel_camera.js";
import { paths } from "../urls.js";

const NOVEL_VIEW_WIDTH = 192;

export function novelView(jobId, config, cameras) {
  const camera = createNovelCamera(config, cameras);
  const img = h("img", { class: "novel", id: `novel-${jobId}`, alt: "novel view (drag to move the camera)" });
  const label = h("p", { class: "muted", id: `novel-label-${jobId}` },
    "Drag the image to move the camera; each position is rendered by the service.");
  const freeToggle = h("input", { type: "checkbox", id: `free-${jobId}`, disabled: !camera.canFollowPath });
  const toggleLabel = h("label", { class: "toggle", title: camera.canFollowPath
    ? "off: the camera moves along the registered cameras; on: it orbits the scene's centre freely"
    : "the NeRF was not trained on a reconstruction: no registered cameras to follow" }, freeToggle, " free orbit");
  const width = NOVEL_VIEW_WIDTH;
  const height = Math.max(8, Math.round((NOVEL_VIEW_WIDTH * config.camera.height) / config.camera.width));
  let busy = false, pending = false, dragging = null, renders = 0;
  const showMode = () => {
    freeToggle.checked = camera.free;
    img.dataset.mode = camera.free ? "free" : "path";
  };
  const request = async () => {
    if (busy) { pending = true; return; }
    busy = true; pending = false;
    const description = camera.describe();
    try {
      const url = await blobUrl(paths.nerf(jobId, "render"), { method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ ...camera.renderCamera(), width, height }) });
      if (img.src) URL.revokeObjectURL(img.src);
      img.src = url;
      img.dataset.renders = String(++renders);
      label.textContent = description;
    } catch (error) {
      label.textContent = error.message;
    } finally {
      busy = false;
      if (pending) request();
    }
  };
  freeToggle.addEventListener("change", () => {
    if (camera.setFree(freeToggle.checked)) request();
    showMode();
  });
  img.addEventListener("pointerdown", (e) => { dragging = [e.clientX, e.clientY]; img.setPointerCapture(e.pointerId); });
  img.addEventListener("pointerup", () => { dragging = null; });
  img.addEventListener("pointermove", (e) => {
    if (!dragging) return;
    const moved = camera.drag(e.clientX - dragging[0], e.clientY - dragging[1], img.clientWidth);
    dragging = [e.clientX, e.clientY];
    if (moved) request();
  });
  img.addEventListener("dragstart", (e) => e.preventDefault());
  showMode();
  request();
  return h("div", {}, img, h("p", {}, toggleLabel), label);
}
