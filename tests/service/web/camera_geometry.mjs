// Registered cameras for the tests: world-to-camera R (OpenCV axes) looking from C at a target.
const sub = (p, q) => p.map((c, i) => c - q[i]);
const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
const normalize = (v) => { const n = Math.hypot(...v); return v.map((c) => c / n); };

// Rows of R are the camera's x (right), y (down) and z (forward) axes in the world.
export function lookingAt(image, C, target = [0, 0, 0], up = [0, 0, 1]) {
  const z = normalize(sub(target, C)), x = normalize(cross(z, up)), y = cross(z, x);
  return { image, R: [x, y, z], C };
}

// n cameras on a circle of `radius` at height `height` about the z axis, at the given angles (degrees).
export const onCircle = (angles, radius = 4, height = 1) => angles.map((deg, k) => {
  const a = (deg * Math.PI) / 180;
  return lookingAt(`${String(k).padStart(4, "0")}.png`, [radius * Math.sin(a), -radius * Math.cos(a), height]);
});

export function assertClose(assert, actual, expected, tolerance = 1e-9, message = "") {
  const flat = (v) => (Array.isArray(v) ? v.flat(Infinity) : [v]);
  const [a, e] = [flat(actual), flat(expected)];
  assert.equal(a.length, e.length, message);
  a.forEach((x, i) => assert.ok(Math.abs(x - e[i]) <= tolerance, `${message} [${i}]: ${x} vs ${e[i]}`));
}
