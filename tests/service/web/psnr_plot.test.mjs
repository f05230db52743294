// The training curve's data and axes (service/web/js/psnr_plot.js).
import assert from "node:assert/strict";
import { test } from "node:test";

import { psnrAxis, psnrSeries } from "../../../service/web/js/psnr_plot.js";

test("training and validation PSNR are separate series of [step, dB]", () => {
  const metrics = [{ step: 1, psnr: 10 }, { step: 2, psnr: 11, val_psnr: 9.5 }, { step: 3, loss: 0.1 }];
  assert.deepEqual(psnrSeries(metrics), { train: [[1, 10], [2, 11]], val: [[2, 9.5]] });
});

test("the axes span whole decibels around every value and at least one step", () => {
  assert.deepEqual(psnrAxis([[10, 12.3], [20, 17.8], [30, 9.6]]), { maxStep: 30, lo: 9, hi: 18 });
  assert.deepEqual(psnrAxis([[0, 20]]), { maxStep: 1, lo: 20, hi: 21 });
});
