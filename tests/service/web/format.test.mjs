// The text the pages show for numbers, metrics and the service's errors (service/web/js/format.js).
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  barWidth, checkpointTags, decibels, degrees, expectedTime, failureMessage, heldOutCaption, isActive, latestMetrics, megabytes,
  percent, reconstructionSummary, trainingSummary,
} from "../../../service/web/js/format.js";

test("progress reads as a whole percentage and fills a clamped bar", () => {
  assert.equal(percent(0.426), "43%");
  assert.equal(percent(1), "100%");
  assert.equal(barWidth(0.4267), "42.7%");
  assert.equal(barWidth(1.5), "100.0%");
  assert.equal(barWidth(-0.2), "0.0%");
  assert.equal(barWidth(undefined), "0.0%");
});

test("sizes, PSNR and angles have their units", () => {
  assert.equal(megabytes(12_345_678), "12.3 MB");
  assert.equal(decibels(23.456), "23.46 dB");
  assert.equal(degrees(Math.PI / 2), "90°");
  assert.equal(degrees(-0.3), "-17°");
});

test("only queued and running jobs are active", () => {
  assert.deepEqual(["queued", "running", "succeeded", "failed", "cancelled"].map(isActive),
    [true, true, false, false, false]);
});

test("a failure names the status and the service's detail, FastAPI's validation list flattened", () => {
  assert.equal(failureMessage(404, "Not Found", { detail: "job abc not found" }), "404 Not Found: job abc not found");
  assert.equal(
    failureMessage(422, "Unprocessable Entity", { detail: [
      { loc: ["body", "images"], msg: "Field required" }, { loc: ["query", "limit"], msg: "too big" }] }),
    "422 Unprocessable Entity: images: Field required; query.limit: too big");
  assert.equal(failureMessage(500, "", null), "500 ");
  assert.match(failureMessage(401, "Unauthorized", { detail: "missing token" }), /missing token \(enter the service's API token/);
});

test("the training summary gives the latest training and validation PSNR", () => {
  const metrics = [{ step: 10, psnr: 12.5 }, { step: 20, val_psnr: 14.25 }, { step: 30, psnr: 15 }];
  assert.deepEqual(latestMetrics(metrics), { train: metrics[2], val: metrics[1] });
  assert.equal(trainingSummary("running", metrics),
    "running; step 30, training PSNR 15.00 dB, validation PSNR 14.25 dB at step 20");
  assert.equal(trainingSummary("queued", []), "queued; step 0");
});

test("a reconstruction's summary counts cameras and points, with the RMS when measured", () => {
  const model = { cameras: [{}, {}, {}],
                  statistics: { images_total: 4, points: 812, reprojection_error_px: { after_ba: { rms: 0.61234 } } } };
  assert.equal(reconstructionSummary(model), "3 of 4 images registered, 812 points, reprojection RMS 0.612 px. ");
  assert.equal(reconstructionSummary({ cameras: [], statistics: {} }), "0 of ? images registered, ? points. ");
});

test("checkpoints and held-out views are labelled", () => {
  assert.equal(checkpointTags({ is_latest: true, is_best: true }), "latest, best");
  assert.equal(checkpointTags({ is_latest: false, is_best: false }), "");
  assert.equal(heldOutCaption({ image: "0000.png", psnr: 18.123, ssim: 0.5 }), "0000.png: PSNR 18.12 dB, SSIM 0.500");
});

test("a scene's expected time reads in whole minutes, rounded up; none for a step count", () => {
  assert.equal(expectedTime({ reconstruction: 20, training: 600, views: 120, total: 740 }),
    "expected about 13 min in all on a CPU");
  assert.equal(expectedTime(null), "");
});
