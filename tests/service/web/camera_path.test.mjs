// Poses of the novel view (service/web/js/camera_path.js): registered cameras as OpenGL camera-to-world
// matrices, the path through them in capture order, interpolation along it, and the free orbit.
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  cameraPath, cameraToWorld, clampPosition, orbitAngles, orbitEye, poseAt, quaternionOf, rotationOf, slerp,
  startPosition,
} from "../../../service/web/js/camera_path.js";
import { assertClose, lookingAt, onCircle } from "./camera_geometry.mjs";

const column = (m, k) => [m[0][k], m[1][k], m[2][k]];
const frame = { target: [0, 0, 0], up: [0, 0, 1] };

test("a registered camera's camera-to-world looks down -z from its centre with y up (OpenGL axes)", () => {
  assert.deepEqual(cameraToWorld({ R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], C: [1, 2, 3] }),
    [[1, -0, -0, 1], [0, -1, -0, 2], [0, -0, -1, 3], [0, 0, 0, 1]]);
  const camera = lookingAt("a.png", [3, -4, 2]);
  const c2w = cameraToWorld(camera);
  assertClose(assert, column(c2w, 3), [3, -4, 2]);
  assertClose(assert, column(c2w, 2).map((c) => -c), camera.R[2]); // -z: the viewing direction
  assert.ok(column(c2w, 1)[2] > 0, "the image's up points up in the world");
});

test("rotations survive the round trip through quaternions, also near 180 degrees", () => {
  const rotations = [
    [[1, 0, 0], [0, 1, 0], [0, 0, 1]], [[1, 0, 0], [0, -1, 0], [0, 0, -1]], [[-1, 0, 0], [0, 1, 0], [0, 0, -1]],
    [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], lookingAt("", [3, -4, 2]).R, lookingAt("", [-1, 5, -2]).R,
  ];
  for (const R of rotations) assertClose(assert, rotationOf(quaternionOf(R)), R, 1e-12, JSON.stringify(R));
});

test("slerp runs along the shorter arc at constant speed", () => {
  const about = (deg) => [Math.cos((deg * Math.PI) / 360), 0, 0, Math.sin((deg * Math.PI) / 360)]; // about z
  assertClose(assert, slerp(about(0), about(90), 0.5), about(45), 1e-12);
  assertClose(assert, slerp(about(0), about(90), 0), about(0), 1e-12);
  assertClose(assert, slerp(about(0), about(90), 1), about(90), 1e-12);
  assertClose(assert, slerp(about(10), about(30).map((c) => -c), 0.5), about(20), 1e-12); // q and -q: one rotation
  assertClose(assert, slerp(about(10), about(10.01), 0.5), about(10.005), 1e-9);
});

test("a forward-facing arc is ordered along the arc, open, running to the cameras' right", () => {
  const cameras = onCircle([-30, -15, 0, 15, 30]); // straddles the angle where atan2 wraps around
  const shuffled = [cameras[3], cameras[0], cameras[4], cameras[2], cameras[1]];
  const path = cameraPath(shuffled, frame);
  assert.equal(path.closed, false);
  assert.deepEqual(path.stops.map((s) => s.image), cameras.map((c) => c.image));
  const flipped = cameraPath(shuffled, { target: [0, 0, 0], up: [0, 0, -1] });
  assert.deepEqual(flipped.stops.map((s) => s.image), cameras.map((c) => c.image), "whichever way up points");
});

test("cameras all around the scene close into a ring; a few or a half circle do not", () => {
  const ring = cameraPath(onCircle([0, 45, 90, 135, 180, 225, 270, 315]), frame);
  assert.equal(ring.closed, true);
  assert.equal(cameraPath(onCircle([0, 120, 240]), frame).closed, false);
  assert.equal(cameraPath(onCircle([0, 30, 60, 90, 120, 150, 180]), frame).closed, false);
});

test("at each stop the pose is that camera's own; between two, centres and rotations interpolate", () => {
  const cameras = onCircle([-20, 0, 20]);
  const path = cameraPath(cameras, frame);
  cameras.forEach((camera, k) => {
    const pose = poseAt(path, k);
    assertClose(assert, pose.c2w, cameraToWorld(camera), 1e-12, camera.image);
    assert.equal(pose.nearest, camera.image);
  });
  const half = poseAt(path, 0.5);
  assertClose(assert, column(half.c2w, 3), cameras[0].C.map((c, i) => (c + cameras[1].C[i]) / 2), 1e-12);
  // The two cameras differ by 20 degrees about the vertical: halfway is the rotation of the camera at -10.
  const halfway = onCircle([-10])[0];
  assertClose(assert, half.c2w.map((row) => row.slice(0, 3)).slice(0, 3),
    cameraToWorld(halfway).map((row) => row.slice(0, 3)).slice(0, 3), 1e-12, "the rotation halfway");
  assert.equal(poseAt(path, 0.4).nearest, cameras[0].image);
  assert.equal(poseAt(path, 0.6).nearest, cameras[1].image);
});

test("an open path is clamped to its captured span; a ring wraps around", () => {
  const path = cameraPath(onCircle([-20, 0, 20]), frame);
  assert.equal(clampPosition(path, -3), 0);
  assert.equal(clampPosition(path, 7.5), 2);
  assertClose(assert, poseAt(path, 99).c2w, poseAt(path, 2).c2w);
  const ring = cameraPath(onCircle([0, 60, 120, 180, 240, 300]), frame);
  assert.equal(clampPosition(ring, 6.5), 0.5);
  assert.equal(clampPosition(ring, -0.5), 5.5);
  assertClose(assert, poseAt(ring, 5.5).c2w.map((row) => row[3]).slice(0, 3),
    ring.stops[5].centre.map((c, i) => (c + ring.stops[0].centre[i]) / 2), 1e-12, "between the last and the first");
});

test("the view starts in the middle of an open path, at the first stop of a ring", () => {
  assert.equal(startPosition(cameraPath(onCircle([-20, 0, 20, 40]), frame)), 1);
  assert.equal(startPosition(cameraPath(onCircle([-20, 0, 20]), frame)), 1);
  assert.equal(startPosition(cameraPath(onCircle([0]), frame)), 0);
  assert.equal(startPosition(cameraPath(onCircle([0, 60, 120, 180, 240, 300]), frame)), 0);
});

test("the free orbit's eye and its angles are inverse to each other", () => {
  const orbit = { target: [1, -2, 0.5], up: [0, 0.6, 0.8], radius: 3 };
  for (const [azimuth, elevation] of [[0, 0.3], [2.5, -1.2], [-1, 0]]) {
    const eye = orbitEye(orbit, azimuth, elevation);
    assertClose(assert, Math.hypot(...eye.map((c, i) => c - orbit.target[i])), 3, 1e-12);
    const angles = orbitAngles(orbit, eye);
    assertClose(assert, [angles.azimuth, angles.elevation, angles.radius], [azimuth, elevation, 3], 1e-12);
  }
});
