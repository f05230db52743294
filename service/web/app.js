// The sfmnerf web app: a hash-routed single page on the service's REST API (/v1), nothing else.
// Pages: #/ (scenes and jobs), #/new (upload), #/jobs/{id}, #/scenes/{id}. Every API error is shown as the
// service's `detail` message; an unexpected page error as one readable line, never a stack trace.
import { parsePly, showReconstruction } from "./viewer.js";

const TOKEN_KEY = "sfmnerf.token";
const POLL_MS = 1500;
const LOG_LINES_KEPT = 300;
const NOVEL_VIEW_WIDTH = 192;
const ACTIVE = new Set(["queued", "running"]);

// ---- API ------------------------------------------------------------------------------------------------

class ApiError extends Error {}

function authHeaders() {
  const token = localStorage.getItem(TOKEN_KEY);
  return token ? { Authorization: `Bearer ${token}` } : {};
}

async function describeFailure(response) {
  let detail = "";
  try {
    const body = await response.json();
    if (typeof body.detail === "string") detail = body.detail;
    else if (Array.isArray(body.detail)) {
      detail = body.detail.map((e) => `${(e.loc || []).filter((x) => x !== "body").join(".")}: ${e.msg}`).join("; ");
    }
  } catch { /* not JSON: the status line says enough */ }
  const hint = response.status === 401 ? " (enter the service's API token at the top right)" : "";
  return `${response.status} ${response.statusText || ""}${detail ? ": " + detail : ""}${hint}`.replace(/\s+/g, " ");
}

async function api(path, options = {}) {
  let response;
  try {
    response = await fetch(path, { ...options, headers: { ...authHeaders(), ...(options.headers || {}) } });
  } catch (error) {
    throw new ApiError(`cannot reach the service (${error.message})`);
  }
  if (!response.ok) throw new ApiError(`${options.method || "GET"} ${path}: ${await describeFailure(response)}`);
  return response;
}

const getJson = async (path) => (await api(path)).json();
const postJson = async (path, body) => (await api(path, {
  method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) })).json();

async function blobUrl(path, options) {
  return URL.createObjectURL(await (await api(path, options)).blob());
}

async function download(path, filename) {
  const link = Object.assign(document.createElement("a"), { href: await blobUrl(path), download: filename });
  link.click();
}

// ---- page helpers ---------------------------------------------------------------------------------------

function showError(message) {
  const box = document.getElementById("error");
  box.textContent = message;
  box.hidden = !message;
}

function h(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes)) {
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(node.dataset, value);
    else if (value !== undefined && value !== null && value !== false) node.setAttribute(key, value);
  }
  node.append(...children.flat().filter((c) => c !== null && c !== undefined));
  return node;
}

const progressBar = (fraction) => h("span", { class: "bar", title: `${Math.round(100 * fraction)}%` },
  h("span", { style: `width:${(100 * fraction).toFixed(1)}%` }));
const stateText = (state) => h("span", { class: `state-${state}` }, state);
const when = (iso) => (iso ? new Date(iso).toLocaleString() : "");

// Runs `step` now and every POLL_MS until it returns false or the page changes; errors are shown, not fatal.
function poll(page, step) {
  const tick = async () => {
    if (page.closed) return;
    let again = true;
    try {
      again = (await step()) !== false;
      showError("");
    } catch (error) {
      showError(error.message);
    }
    if (again && !page.closed) page.timers.push(setTimeout(tick, POLL_MS));
  };
  tick();
}

// Guard for one-shot loads inside a page: shows the error in place of the section.
async function section(container, load) {
  try {
    await load();
  } catch (error) {
    container.replaceChildren(h("p", { class: "muted" }, error.message));
  }
}

// ---- #/ : scenes and jobs -------------------------------------------------------------------------------

function listPage(main, page) {
  const scenes = h("tbody"), jobs = h("tbody");
  main.append(
    h("h1", {}, "Scenes and jobs"),
    h("p", {}, h("a", { href: "#/new" }, "Upload photos"), " to start a reconstruction or a whole scene."),
    h("h2", {}, "Scenes"),
    h("table", { id: "scenes" }, h("thead", {}, h("tr", {}, ["Scene", "State", "Stage", "Progress", "Created"].map((t) => h("th", {}, t)))), scenes),
    h("h2", {}, "Jobs"),
    h("table", { id: "jobs" }, h("thead", {}, h("tr", {}, ["Job", "Kind", "State", "Stage", "Progress", "Created"].map((t) => h("th", {}, t)))), jobs),
  );
  poll(page, async () => {
    const [sceneList, jobList] = await Promise.all([getJson("/v1/scenes?limit=50"), getJson("/v1/jobs?limit=100")]);
    scenes.replaceChildren(...sceneList.items.map((s) => h("tr", { dataset: { id: s.id, state: s.state } },
      h("td", {}, h("a", { href: `#/scenes/${s.id}` }, s.id.slice(0, 8))), h("td", {}, stateText(s.state)),
      h("td", {}, s.stage || ""), h("td", {}, progressBar(s.progress), ` ${Math.round(100 * s.progress)}%`),
      h("td", {}, when(s.created_at)))));
    if (!sceneList.items.length) scenes.append(h("tr", {}, h("td", { colspan: 5, class: "muted" }, "none yet")));
    jobs.replaceChildren(...jobList.items.map((j) => h("tr", { dataset: { id: j.id, state: j.state } },
      h("td", {}, h("a", { href: `#/jobs/${j.id}` }, j.id.slice(0, 8))), h("td", {}, j.kind),
      h("td", {}, stateText(j.state)), h("td", {}, j.stage || ""),
      h("td", {}, progressBar(j.progress), ` ${Math.round(100 * j.progress)}%`), h("td", {}, when(j.created_at)))));
    if (!jobList.items.length) jobs.append(h("tr", {}, h("td", { colspan: 6, class: "muted" }, "none yet")));
  });
}

// ---- #/new : upload -------------------------------------------------------------------------------------

const MATCH_FILE = /^matching\d+\.txt$/i;
const IMAGE_FILE = /\.(png|jpe?g)$/i;

function uploadPage(main) {
  const chosen = { images: [], matches: [], calibration: null, zip: null };
  const lists = h("div");
  const picker = h("input", { type: "file", multiple: true, hidden: true, id: "files",
    onchange: () => addFiles(picker.files) });
  const drop = h("div", { class: "drop", id: "drop", onclick: () => picker.click() },
    "Drop photos here (PNG/JPEG or one .zip of them), with optional matching<i>.txt files and calibration.txt — or click to choose");
  const addFiles = (files) => {
    for (const file of files) {
      if (MATCH_FILE.test(file.name)) chosen.matches.push(file);
      else if (/\.txt$/i.test(file.name)) chosen.calibration = file;
      else if (/\.zip$/i.test(file.name)) chosen.zip = file;
      else if (IMAGE_FILE.test(file.name)) chosen.images.push(file);
      else showError(`${file.name}: not a photo (PNG/JPEG), a zip, a matching<i>.txt or a calibration .txt; left out`);
    }
    const names = (files) => h("ul", { class: "files" }, files.map((f) => h("li", {}, f.name)));
    lists.replaceChildren(
      h("p", {}, `${chosen.images.length} photo(s)${chosen.zip ? ` and ${chosen.zip.name}` : ""}, `
        + `${chosen.matches.length} match file(s), calibration: ${chosen.calibration ? chosen.calibration.name : "none"}`),
      names(chosen.images));
  };
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); addFiles(e.dataTransfer.files); });

  const field = (label, input) => h("label", {}, label, input);
  const what = h("select", { name: "what", id: "what" },
    h("option", { value: "scene" }, "Scene: reconstruction → NeRF → novel views"),
    h("option", { value: "reconstruction" }, "Reconstruction only"));
  const K = h("input", { name: "K", size: 36, placeholder: "fx 0 cx 0 fy cy 0 0 1 (if no calibration file)" });
  const features = h("select", { name: "features" }, ["auto", "matches", "sift"].map((v) => h("option", { value: v }, v)));
  const ransac = h("input", { name: "ransac_threshold_px", type: "number", step: "any", min: 0, placeholder: "default" });
  const ba = h("input", { name: "ba_max_iterations", type: "number", min: 1, placeholder: "default" });
  const model = h("select", { name: "model" }, ["fast", "vanilla"].map((v) => h("option", { value: v }, v)));
  const minutes = h("input", { name: "minutes", type: "number", step: "any", min: 0, placeholder: "default" });
  const steps = h("input", { name: "steps", type: "number", min: 1, placeholder: "or steps" });
  const frames = h("input", { name: "orbit_frames", type: "number", min: 1, placeholder: "36" });
  const trainSide = h("input", { name: "train_max_side", type: "number", min: 8, placeholder: "for the budget" });
  const nerfRow = h("div", { class: "row" }, field("NeRF model", model), field("Training minutes", minutes),
    field("or steps", steps), field("Orbit video frames", frames), field("Training photo size (px)", trainSide));
  what.addEventListener("change", () => { nerfRow.hidden = what.value !== "scene"; });
  const submit = h("button", { type: "submit", id: "submit" }, "Start");

  const form = h("form", { id: "upload", onsubmit: async (event) => {
    event.preventDefault();
    const body = new FormData();
    chosen.images.forEach((f) => body.append("images", f, f.name));
    chosen.matches.forEach((f) => body.append("matches", f, f.name));
    if (chosen.calibration) body.append("calibration", chosen.calibration, chosen.calibration.name);
    if (chosen.zip) body.append("photos_zip", chosen.zip, chosen.zip.name);
    const set = (name, value) => { if (value !== "" && value !== null) body.append(name, value); };
    set("K", K.value.trim()); set("features", features.value);
    set("ransac_threshold_px", ransac.value); set("ba_max_iterations", ba.value);
    const scene = what.value === "scene";
    if (scene) {
      set("model", model.value); set("minutes", minutes.value); set("steps", steps.value); set("orbit_frames", frames.value);
      set("train_max_side", trainSide.value);
    }
    if (!scene && chosen.zip) { showError("a zip of photos starts a scene; for a reconstruction drop the photos themselves"); return; }
    submit.disabled = true;
    try {
      const created = await (await api(scene ? "/v1/scenes" : "/v1/reconstructions", { method: "POST", body })).json();
      showError("");
      location.hash = scene ? `#/scenes/${created.id}` : `#/jobs/${created.id}`;
    } catch (error) {
      showError(error.message);
    } finally {
      submit.disabled = false;
    }
  } },
  drop, picker, lists,
  h("div", { class: "row" }, field("Start", what), field("K", K), field("Features", features),
    field("RANSAC threshold (px)", ransac), field("BA iterations", ba)),
  nerfRow, submit);
  main.append(h("h1", {}, "New upload"), form);
}

// ---- job panels -----------------------------------------------------------------------------------------

function logPanel(page, jobId) {
  const pre = h("pre", { class: "log", id: `log-${jobId}` });
  let offset = 0, lines = [];
  poll(page, async () => {
    const chunk = await getJson(`/v1/jobs/${jobId}/logs?offset=${offset}&limit=1000`);
    offset = chunk.next_offset;
    if (chunk.lines.length) {
      lines = lines.concat(chunk.lines).slice(-LOG_LINES_KEPT);
      const atBottom = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
      pre.textContent = lines.join("\n");
      if (atBottom) pre.scrollTop = pre.scrollHeight;
    }
    const job = await getJson(`/v1/jobs/${jobId}`);
    return ACTIVE.has(job.state) || chunk.lines.length > 0;
  });
  return h("div", { class: "panel" }, h("h2", {}, "Log"), pre);
}

function reconstructionPanel(page, jobId) {
  const stats = h("div"), view = h("div", { class: "view3d", id: "view3d" }), figures = h("div", { class: "grid figures" });
  const panel = h("div", { class: "panel", id: `reconstruction-${jobId}` }, h("h2", {}, "Reconstruction"), stats,
    view, h("h2", {}, "Figures"), figures);
  section(panel, async () => {
    const model = await getJson(`/v1/reconstructions/${jobId}`);
    const s = model.statistics;
    const rms = s.reprojection_error_px?.after_ba?.rms;
    const downloads = ["points.ply", "colmap.zip", "transforms.json"].map((name) =>
      h("button", { class: "secondary", onclick: () => download(model.files[name], name).catch((e) => showError(e.message)) }, name));
    stats.replaceChildren(h("p", {}, `${model.cameras.length} of ${s.images_total ?? "?"} images registered, `
      + `${s.points ?? "?"} points${rms !== undefined ? `, reprojection RMS ${rms.toFixed(3)} px` : ""}. `,
      ...model.unregistered.map((u) => h("span", { class: "muted" }, `${u.image}: ${u.reason}. `))),
      h("p", {}, "Downloads: ", ...downloads));
    const ply = parsePly(await (await api(model.files["points.ply"])).arrayBuffer());
    page.disposers.push(showReconstruction(view, {
      points: ply, cameras: model.cameras, intrinsics: model.intrinsics,
      registrationOrder: s.registration_order || model.cameras.map((c) => c.image) }).dispose);
    for (const [name, url] of Object.entries(model.files).filter(([n]) => n.startsWith("figures/"))) {
      figures.append(h("figure", {}, h("img", { src: await blobUrl(url), alt: name }), h("figcaption", {}, name.slice(8))));
    }
  });
  return panel;
}

function drawCurve(canvas, metrics) {
  const train = metrics.filter((m) => m.psnr != null).map((m) => [m.step, m.psnr]);
  const val = metrics.filter((m) => m.val_psnr != null).map((m) => [m.step, m.val_psnr]);
  const all = train.concat(val);
  const ratio = window.devicePixelRatio || 1;
  canvas.width = canvas.clientWidth * ratio; canvas.height = canvas.clientHeight * ratio;
  const g = canvas.getContext("2d");
  g.scale(ratio, ratio);
  const W = canvas.clientWidth, H = canvas.clientHeight, pad = 36;
  g.clearRect(0, 0, W, H);
  g.font = "11px system-ui"; g.fillStyle = "#687084";
  if (!all.length) { g.fillText("no metrics yet", pad, H / 2); return; }
  const maxStep = Math.max(...all.map((p) => p[0]), 1);
  const lo = Math.floor(Math.min(...all.map((p) => p[1]))), hi = Math.ceil(Math.max(...all.map((p) => p[1])) + 0.01);
  const x = (s) => pad + ((W - pad - 8) * s) / maxStep, y = (v) => H - pad + 12 - ((H - pad - 4) * (v - lo)) / Math.max(hi - lo, 1e-6);
  g.strokeStyle = "#d9dde6"; g.beginPath(); g.moveTo(pad, 4); g.lineTo(pad, H - pad + 12); g.lineTo(W - 8, H - pad + 12); g.stroke();
  g.fillText(`${hi} dB`, 2, 12); g.fillText(`${lo} dB`, 2, H - pad + 12); g.fillText(`step ${maxStep}`, W - 70, H - 6);
  const line = (points, colour, dots) => {
    g.strokeStyle = g.fillStyle = colour; g.beginPath();
    points.forEach(([s, v], i) => (i ? g.lineTo(x(s), y(v)) : g.moveTo(x(s), y(v))));
    g.stroke();
    if (dots) points.forEach(([s, v]) => g.fillRect(x(s) - 2, y(v) - 2, 4, 4));
  };
  line(train, "#2f6fdb", train.length < 30); line(val, "#e07b00", true);
  g.fillStyle = "#2f6fdb"; g.fillText("training PSNR", pad + 8, 14); g.fillStyle = "#e07b00"; g.fillText("validation PSNR", pad + 100, 14);
}

// Drag on the image to orbit; each new angle asks the service for a render, shown as soon as it arrives.
function novelView(jobId, config) {
  const img = h("img", { class: "novel", id: `novel-${jobId}`, alt: "novel view (drag to orbit)" });
  const label = h("p", { class: "muted" }, "Drag the image to orbit; each position is rendered by the service.");
  const { orbit, normalization, camera } = config;
  const scale = normalization?.scale ?? 1, centre = normalization?.centre ?? [0, 0, 0];
  const target = orbit.target.map((v, i) => v / scale + centre[i]), radius = orbit.radius / scale, up = orbit.up;
  const width = NOVEL_VIEW_WIDTH, height = Math.max(8, Math.round((NOVEL_VIEW_WIDTH * camera.height) / camera.width));
  // An orthonormal frame (a, b) of the plane orthogonal to `up`, for azimuth around it.
  const norm = (v) => { const n = Math.hypot(...v) || 1; return v.map((c) => c / n); };
  const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
  const a = norm(cross(up, Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0])), b = cross(up, a);
  let azimuth = 0, elevation = 0.3, busy = false, pending = false, dragging = null, renders = 0;
  const request = async () => {
    if (busy) { pending = true; return; }
    busy = true; pending = false;
    const dir = [0, 1, 2].map((i) => Math.cos(elevation) * (Math.cos(azimuth) * a[i] + Math.sin(azimuth) * b[i]) + Math.sin(elevation) * up[i]);
    try {
      const url = await blobUrl(`/v1/nerf/${jobId}/render`, { method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ eye: target.map((t, i) => t + radius * dir[i]), look_at: target, up, frame: "data", allow_empty_view: true, width, height }) });
      if (img.src) URL.revokeObjectURL(img.src);
      img.src = url;
      img.dataset.renders = String(++renders);
      label.textContent = `azimuth ${Math.round((azimuth * 180) / Math.PI)}°, elevation ${Math.round((elevation * 180) / Math.PI)}°`;
    } catch (error) {
      label.textContent = error.message;
    } finally {
      busy = false;
      if (pending) request();
    }
  };
  img.addEventListener("pointerdown", (e) => { dragging = [e.clientX, e.clientY]; img.setPointerCapture(e.pointerId); });
  img.addEventListener("pointerup", () => { dragging = null; });
  img.addEventListener("pointermove", (e) => {
    if (!dragging) return;
    azimuth -= (e.clientX - dragging[0]) * 0.01;
    elevation = Math.max(-1.4, Math.min(1.4, elevation + (e.clientY - dragging[1]) * 0.01));
    dragging = [e.clientX, e.clientY];
    request();
  });
  img.addEventListener("dragstart", (e) => e.preventDefault());
  request();
  return h("div", {}, img, label);
}

function nerfPanel(page, jobId) {
  const canvas = h("canvas", { class: "plot", id: `psnr-${jobId}` });
  const summary = h("p", { class: "muted" }, "waiting for the first metrics…");
  const validation = h("div", { class: "renders" }), novel = h("div"), video = h("div"), checkpoints = h("tbody");
  let lastValidation = null, shownNovel = false;
  const videoButton = h("button", { class: "secondary", onclick: async () => {
    try {
      await postJson(`/v1/nerf/${jobId}/video`, { num_frames: 24, width: 160, height: 120 });
      video.replaceChildren(h("p", { class: "muted" }, "rendering the orbit video…"));
      showVideo();
    } catch (error) { showError(error.message); }
  } }, "Render an orbit video");
  const showVideo = () => poll(page, async () => {
    try {
      video.replaceChildren(h("img", { src: await blobUrl(`/v1/nerf/${jobId}/video`), alt: "orbit video", id: `video-${jobId}` }));
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
    const nerf = await getJson(`/v1/nerf/${jobId}`);
    drawCurve(canvas, nerf.metrics);
    const last = [...nerf.metrics].reverse();
    const train = last.find((m) => m.psnr != null), val = last.find((m) => m.val_psnr != null);
    summary.textContent = `${nerf.job.state}; step ${train?.step ?? 0}` + (train ? `, training PSNR ${train.psnr.toFixed(2)} dB` : "")
      + (val ? `, validation PSNR ${val.val_psnr.toFixed(2)} dB at step ${val.step}` : "");
    if (val && val.step !== lastValidation) {
      lastValidation = val.step;
      validation.replaceChildren(h("img", { src: await blobUrl(`/v1/nerf/${jobId}/validation`), alt: `validation render at step ${val.step}` }),
        h("p", { class: "muted" }, `step ${val.step}: ground truth | render | depth`));
    }
    const list = await getJson(`/v1/nerf/${jobId}/checkpoints`);
    checkpoints.replaceChildren(...list.map((c) => h("tr", {}, h("td", {}, String(c.step)),
      h("td", {}, [c.is_latest && "latest", c.is_best && "best"].filter(Boolean).join(", ")),
      h("td", {}, c.val_psnr != null ? `${c.val_psnr.toFixed(2)} dB` : ""), h("td", {}, `${(c.size_bytes / 1e6).toFixed(1)} MB`),
      h("td", {}, h("button", { class: "secondary", onclick: () => download(c.url, `step_${c.step}.pt`).catch((e) => showError(e.message)) }, "download")))));
    if (list.length && !shownNovel && nerf.config?.orbit) {
      shownNovel = true;
      novel.replaceChildren(novelView(jobId, nerf.config));
    }
    return ACTIVE.has(nerf.job.state) || !shownNovel && list.length > 0;
  });
  return h("div", { class: "panel", id: `nerf-${jobId}` }, h("h2", {}, "NeRF training"), summary, canvas,
    h("div", { class: "grid" },
      h("div", {}, h("h2", {}, "Latest validation render"), validation),
      h("div", {}, h("h2", {}, "Novel view"), novel),
      h("div", {}, h("h2", {}, "Orbit video"), videoButton, video)),
    h("h2", {}, "Checkpoints"),
    h("table", {}, h("thead", {}, h("tr", {}, ["Step", "", "Validation PSNR", "Size", ""].map((t) => h("th", {}, t)))), checkpoints));
}

function actions(kind, id, state, onDeleted) {
  const act = (label, method, path, after) => h("button", { class: "secondary", id: `${label.toLowerCase()}-${id}`, onclick: async () => {
    try { after(await api(path, { method })); } catch (error) { showError(error.message); }
  } }, label);
  const base = kind === "scene" ? `/v1/scenes/${id}` : `/v1/jobs/${id}`;
  const route = kind === "scene" ? "scenes" : "jobs";
  return h("p", {},
    ACTIVE.has(state) ? act("Cancel", "POST", `${base}/cancel`, () => {}) : null, " ",
    ["failed", "cancelled"].includes(state) ? act("Retry", "POST", `${base}/retry`, async (r) => {
      location.hash = `#/${route}/${(await r.json()).id}`;
    }) : null, " ",
    act("Delete", "DELETE", base, onDeleted));
}

// ---- #/jobs/{id} ----------------------------------------------------------------------------------------

function jobPage(main, page, jobId) {
  const head = h("div"), body = h("div");
  main.append(h("h1", {}, `Job ${jobId.slice(0, 8)}`), head, body);
  let shown = false;
  poll(page, async () => {
    const job = await getJson(`/v1/jobs/${jobId}`);
    head.replaceChildren(h("div", { class: "panel", id: "job", dataset: { state: job.state, kind: job.kind } },
      h("p", {}, `${job.kind}: `, stateText(job.state), ` — ${job.stage || ""} `, progressBar(job.progress),
        ` ${Math.round(100 * job.progress)}%`),
      job.error ? h("p", { class: "error" }, job.error) : null,
      job.source_job_id ? h("p", {}, "Source: ", h("a", { href: `#/jobs/${job.source_job_id}` }, job.source_job_id)) : null,
      actions("job", jobId, job.state, () => { location.hash = "#/"; })));
    if (!shown) {
      shown = true;
      if (job.kind === "nerf") body.append(nerfPanel(page, jobId));
      body.append(logPanel(page, jobId));
    }
    if (job.kind === "reconstruction" && job.state === "succeeded" && !body.querySelector(".view3d")) {
      body.prepend(reconstructionPanel(page, jobId));
    }
    return ACTIVE.has(job.state);
  });
}

// ---- #/scenes/{id} --------------------------------------------------------------------------------------

function scenePage(main, page, sceneId) {
  const head = h("div"), body = h("div");
  main.append(h("h1", {}, `Scene ${sceneId.slice(0, 8)}`), head, body);
  const shown = new Set();
  poll(page, async () => {
    const scene = await getJson(`/v1/scenes/${sceneId}`);
    head.replaceChildren(h("div", { class: "panel", id: "scene", dataset: { state: scene.state, stage: scene.stage } },
      h("p", {}, stateText(scene.state), ` — stage ${scene.stage} `, progressBar(scene.progress), ` ${Math.round(100 * scene.progress)}%`),
      scene.error ? h("p", { class: "error" }, scene.error) : null,
      scene.expected_seconds ? h("p", { class: "muted", id: "expected" },
        `expected about ${Math.ceil(scene.expected_seconds.total / 60)} min in all on a CPU`) : null,
      h("table", {}, h("tbody", {}, scene.stages.map((s) => h("tr", {},
        h("td", {}, s.name), h("td", {}, stateText(s.state)), h("td", {}, progressBar(s.progress)),
        h("td", {}, s.job_ids.map((id) => h("a", { href: `#/jobs/${id}` }, `job ${id.slice(0, 8)} `))))))),
      h("pre", { class: "log" }, scene.log.join("\n")),
      actions("scene", sceneId, scene.state, () => { location.hash = "#/"; })));
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
            h("figcaption", {}, `${view.image}: PSNR ${view.psnr.toFixed(2)} dB, SSIM ${view.ssim.toFixed(3)}`)));
        }
      });
    }
    return ACTIVE.has(scene.state);
  });
}

// ---- router ---------------------------------------------------------------------------------------------

let current = null;

function route() {
  if (current) {
    current.closed = true;
    current.timers.forEach(clearTimeout);
    current.disposers.forEach((dispose) => dispose());
  }
  current = { closed: false, timers: [], disposers: [] };
  showError("");
  const main = document.getElementById("main");
  main.replaceChildren();
  const [, kind, id] = location.hash.replace(/^#\/?/, "/").split("/");
  if (kind === "new") uploadPage(main);
  else if (kind === "jobs" && id) jobPage(main, current, id);
  else if (kind === "scenes" && id) scenePage(main, current, id);
  else listPage(main, current);
}

function setUpToken() {
  const input = document.getElementById("token");
  input.value = localStorage.getItem(TOKEN_KEY) || "";
  input.addEventListener("change", () => {
    if (input.value) localStorage.setItem(TOKEN_KEY, input.value);
    else localStorage.removeItem(TOKEN_KEY);
    route();
  });
}

window.addEventListener("error", (event) => showError(`Something went wrong in the page: ${event.message}`));
window.addEventListener("unhandledrejection", (event) => showError(`Something went wrong in the page: ${event.reason?.message || event.reason}`));
window.addEventListener("hashchange", route);
setUpToken();
route();
