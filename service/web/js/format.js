// Text the pages show for numbers, dates, metrics and the service's error bodies. Pure: no DOM, no fetch.

// A job or scene in these states may still change; the pages keep polling it.
export const isActive = (state) => state === "queued" || state === "running";

export const percent = (fraction) => `${Math.round(100 * fraction)}%`;

// CSS width of a progress bar's filled part; out-of-range fractions are clamped.
export const barWidth = (fraction) => `${(100 * Math.min(1, Math.max(0, fraction || 0))).toFixed(1)}%`;

export const megabytes = (bytes) => `${(bytes / 1e6).toFixed(1)} MB`;

export const decibels = (value) => `${value.toFixed(2)} dB`;

export const degrees = (radians) => `${Math.round((radians * 180) / Math.PI)}°`;

export const localTime = (iso) => (iso ? new Date(iso).toLocaleString() : "");

// One line from a failed response: "404 Not Found: job ... not found", FastAPI's validation list flattened to
// "field: message; ...", and a hint on 401.
export function failureMessage(status, statusText, body) {
  let detail = "";
  if (typeof body?.detail === "string") detail = body.detail;
  else if (Array.isArray(body?.detail)) {
    detail = body.detail.map((e) => `${(e.loc || []).filter((x) => x !== "body").join(".")}: ${e.msg}`).join("; ");
  }
  const hint = status === 401 ? " (enter the service's API token at the top right)" : "";
  return `${status} ${statusText || ""}${detail ? ": " + detail : ""}${hint}`.replace(/\s+/g, " ");
}

// The latest training and validation entries of a NeRF's metrics (either may be undefined).
export function latestMetrics(metrics) {
  const newestFirst = [...metrics].reverse();
  return { train: newestFirst.find((m) => m.psnr != null), val: newestFirst.find((m) => m.val_psnr != null) };
}

export function trainingSummary(state, metrics) {
  const { train, val } = latestMetrics(metrics);
  return `${state}; step ${train?.step ?? 0}` + (train ? `, training PSNR ${decibels(train.psnr)}` : "")
    + (val ? `, validation PSNR ${decibels(val.val_psnr)} at step ${val.step}` : "");
}

// "5 of 6 images registered, 2810 points, reprojection RMS 0.612 px. " from GET /v1/reconstructions/{id}.
export function reconstructionSummary(model) {
  const s = model.statistics;
  const rms = s.reprojection_error_px?.after_ba?.rms;
  return `${model.cameras.length} of ${s.images_total ?? "?"} images registered, `
    + `${s.points ?? "?"} points${rms !== undefined ? `, reprojection RMS ${rms.toFixed(3)} px` : ""}. `;
}

export const checkpointTags = (checkpoint) =>
  [checkpoint.is_latest && "latest", checkpoint.is_best && "best"].filter(Boolean).join(", ");

// A scene's expected duration (expected_seconds of GET /v1/scenes/{id}, null for a step count), whole minutes
// rounded up.
export const expectedTime = (expected) =>
  (expected ? `expected about ${Math.ceil(expected.total / 60)} min in all on a CPU` : "");

export const heldOutCaption = (view) =>
  `${view.image}: PSNR ${decibels(view.psnr)}, SSIM ${view.ssim.toFixed(3)}`;
