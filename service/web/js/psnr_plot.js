// The training curve: training and validation PSNR against step, drawn on a canvas. psnrSeries and
// psnrAxis are pure; drawCurve draws.

const PAD_PX = 36;
const TRAIN_COLOUR = "#2f6fdb";
const VAL_COLOUR = "#e07b00";
const DOTS_BELOW_POINTS = 30; // a sparse training curve shows its points

// [[step, psnr]...] of training and of validation entries.
export const psnrSeries = (metrics) => ({
  train: metrics.filter((m) => m.psnr != null).map((m) => [m.step, m.psnr]),
  val: metrics.filter((m) => m.val_psnr != null).map((m) => [m.step, m.val_psnr]),
});

// Axis limits: the last step (at least 1) and whole decibels around every value.
export function psnrAxis(points) {
  const values = points.map((p) => p[1]);
  return { maxStep: Math.max(...points.map((p) => p[0]), 1),
           lo: Math.floor(Math.min(...values)), hi: Math.ceil(Math.max(...values) + 0.01) };
}

export function drawCurve(canvas, metrics) {
  const { train, val } = psnrSeries(metrics);
  const all = train.concat(val);
  const ratio = window.devicePixelRatio || 1;
  canvas.width = canvas.clientWidth * ratio; canvas.height = canvas.clientHeight * ratio;
  const g = canvas.getContext("2d");
  g.scale(ratio, ratio);
  const W = canvas.clientWidth, H = canvas.clientHeight, pad = PAD_PX;
  g.clearRect(0, 0, W, H);
  g.font = "11px system-ui"; g.fillStyle = "#687084";
  if (!all.length) { g.fillText("no metrics yet", pad, H / 2); return; }
  const { maxStep, lo, hi } = psnrAxis(all);
  const x = (s) => pad + ((W - pad - 8) * s) / maxStep, y = (v) => H - pad + 12 - ((H - pad - 4) * (v - lo)) / Math.max(hi - lo, 1e-6);
  g.strokeStyle = "#d9dde6"; g.beginPath(); g.moveTo(pad, 4); g.lineTo(pad, H - pad + 12); g.lineTo(W - 8, H - pad + 12); g.stroke();
  g.fillText(`${hi} dB`, 2, 12); g.fillText(`${lo} dB`, 2, H - pad + 12); g.fillText(`step ${maxStep}`, W - 70, H - 6);
  const line = (points, colour, dots) => {
    g.strokeStyle = g.fillStyle = colour; g.beginPath();
    points.forEach(([s, v], i) => (i ? g.lineTo(x(s), y(v)) : g.moveTo(x(s), y(v))));
    g.stroke();
    if (dots) points.forEach(([s, v]) => g.fillRect(x(s) - 2, y(v) - 2, 4, 4));
  };
  line(train, TRAIN_COLOUR, train.length < DOTS_BELOW_POINTS); line(val, VAL_COLOUR, true);
  g.fillStyle = TRAIN_COLOUR; g.fillText("training PSNR", pad + 8, 14); g.fillStyle = VAL_COLOUR; g.fillText("validation PSNR", pad + 100, 14);
}
