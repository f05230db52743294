// The novel view's camera (service/web/js/novel_camera.js): it starts at a registered camera, a drag moves it
// along the registered cameras within the captured span, and "free" orbits the scene's centre.
import assert from "node:assert/strict";
import { test } from "node:test";

import { cameraToWorld } from "../../../service/web/js/camera_path.js";
import { createNovelCamera } from "../../../service/web/js/novel_camera.js";
import { assertClose, onCircle } from "./camera_geometry.mjs";

// config.json of a NeRF: the orbit in the scene frame, x_scene = scale (x_original - centre).
const normalization = { centre: [10, 20, 30], scale: 0.5 };
const toScene = (p) => p.map((c, i) => normalization.scale * (c - normalization.centre[i]));
const config = { normalization, camera: { width: 400, height: 300 },
                 orbit: { target: toScene([10, 20, 30]), up: [0, 0, 1], radius: 2 } };
// Five photos on a 60 degree arc around the original frame's point (10, 20, 30).
const cameras = onCircle([-30, -15, 0, 15, 30]).map((c) => ({ ...c, C: c.C.map((v, i) => v + normalization.centre[i]) }));
const WIDTH_PX = 400;

test("the view opens at a registered camera's pose: the middle photo of the arc", () => {
  const camera = createNovelCamera(config, [cameras[4], cameras[1], cameras[2], cameras[0], cameras[3]]);
  assert.equal(camera.free, false);
  assert.deepEqual(Object.keys(camera.renderCamera()), ["c2w", "frame"]);
  assert.equal(camera.renderCamera().frame, "data", "the registered cameras' poses are in the data frame");
  assertClose(assert, camera.renderCamera().c2w, cameraToWorld(cameras[2]), 1e-12);
  assert.equal(camera.describe(), "near photo 0002.png (3 of 5 along the path of registered cameras)");
});

test("dragging moves along the registered cameras, the image's width spanning them all", () => {
  const camera = createNovelCamera(config, cameras);
  assert.equal(camera.drag(-WIDTH_PX / 4, 0, WIDTH_PX), true); // drag left: the camera moves right
  assertClose(assert, camera.renderCamera().c2w, cameraToWorld(cameras[3]), 1e-12);
  assert.equal(camera.drag(WIDTH_PX / 8, 0, WIDTH_PX), true);
  assert.equal(camera.position, 2.5);
  assert.equal(camera.drag(0, 50, WIDTH_PX), false, "up and down stay on the path");
});

test("the drag stops at the first and the last photo", () => {
  const camera = createNovelCamera(config, cameras);
  assert.equal(camera.drag(3 * WIDTH_PX, 0, WIDTH_PX), true);
  assertClose(assert, camera.renderCamera().c2w, cameraToWorld(cameras[0]), 1e-12);
  assert.equal(camera.drag(50, 0, WIDTH_PX), false);
  camera.drag(-10 * WIDTH_PX, 0, WIDTH_PX);
  assertClose(assert, camera.renderCamera().c2w, cameraToWorld(cameras[4]), 1e-12);
});

test("free mode orbits the scene's centre from where the camera was, and back on the path where it left", () => {
  const camera = createNovelCamera(config, cameras);
  camera.drag(-WIDTH_PX / 4, 0, WIDTH_PX);
  assert.equal(camera.setFree(true), true);
  assert.equal(camera.setFree(true), false);
  const { eye, look_at: lookAt, up, frame, allow_empty_view: allowEmpty } = camera.renderCamera();
  assert.equal(frame, "data");
  assert.equal(allowEmpty, true, "the free orbit may look away from the scene");
  assertClose(assert, eye, cameras[3].C, 1e-9, "the eye stays where the camera was");
  assertClose(assert, lookAt, [10, 20, 30], 1e-12, "looking at the orbit's target in the original frame");
  assert.deepEqual(up, [0, 0, 1]);
  assert.equal(camera.drag(30, -20, WIDTH_PX), true);
  const moved = camera.renderCamera().eye;
  assertClose(assert, Math.hypot(...moved.map((c, i) => c - lookAt[i])), Math.hypot(...eye.map((c, i) => c - lookAt[i])), 1e-9);
  assert.match(camera.describe(), /^free orbit: azimuth -?\d+°, elevation -?\d+°$/);
  camera.setFree(false);
  assertClose(assert, camera.renderCamera().c2w, cameraToWorld(cameras[3]), 1e-12);
});

test("without registered cameras the view orbits freely from azimuth 0, as before", () => {
  const camera = createNovelCamera(config, []);
  assert.equal(camera.free, true);
  assert.equal(camera.canFollowPath, false);
  assert.equal(camera.setFree(false), false);
  const { eye, look_at: lookAt } = camera.renderCamera();
  assertClose(assert, lookAt, [10, 20, 30], 1e-12);
  assertClose(assert, Math.hypot(...eye.map((c, i) => c - lookAt[i])), config.orbit.radius / normalization.scale, 1e-12);
  assert.equal(camera.describe(), "free orbit: azimuth 0°, elevation 17°");
  for (let k = 0; k < 10; k++) camera.drag(0, 100, WIDTH_PX);
  assert.match(camera.describe(), /elevation 80°$/, "the free orbit stops short of the pole");
});
