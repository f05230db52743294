// Poses for the novel view: a path through the registered cameras, and the free orbit. Pure maths on plain
// arrays. Registered cameras come as GET /v1/reconstructions/{id} gives them: world-to-camera R (OpenCV
// axes: x right, y down, z forward) and centre C. Render requests take camera-to-world matrices in OpenGL
// axes (x right, y up, looking down -z): columns [R^T x, -R^T y, -R^T z | C], in the same world frame.

const dot = (p, q) => p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
const sub = (p, q) => [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
const normalize = (v) => { const n = Math.hypot(...v) || 1; return v.map((c) => c / n); };

// Cameras more evenly spread than this around the scene (no gap wider) close into a ring.
const MAX_RING_GAP = Math.PI / 2;
const MIN_RING_CAMERAS = 4;

// 4x4 OpenGL camera-to-world of a registered camera.
export function cameraToWorld({ R, C }) {
  return [0, 1, 2].map((i) => [R[0][i], -R[1][i], -R[2][i], C[i]]).concat([[0, 0, 0, 1]]);
}

// Unit quaternion [w, x, y, z] of a rotation matrix (the 3x3 top-left of m).
export function quaternionOf(m) {
  const trace = m[0][0] + m[1][1] + m[2][2];
  let q;
  if (trace > 0) {
    const s = 2 * Math.sqrt(1 + trace);
    q = [s / 4, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s];
  } else if (m[0][0] > m[1][1] && m[0][0] > m[2][2]) {
    const s = 2 * Math.sqrt(1 + m[0][0] - m[1][1] - m[2][2]);
    q = [(m[2][1] - m[1][2]) / s, s / 4, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s];
  } else if (m[1][1] > m[2][2]) {
    const s = 2 * Math.sqrt(1 + m[1][1] - m[0][0] - m[2][2]);
    q = [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, s / 4, (m[1][2] + m[2][1]) / s];
  } else {
    const s = 2 * Math.sqrt(1 + m[2][2] - m[0][0] - m[1][1]);
    q = [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, s / 4];
  }
  const n = Math.hypot(...q);
  return q.map((c) => c / n);
}

// 3x3 rotation matrix of a unit quaternion [w, x, y, z].
export function rotationOf([w, x, y, z]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

// Spherical interpolation from q0 (f = 0) to q1 (f = 1) along the shorter arc.
export function slerp(q0, q1, f) {
  let cosine = dot(q0.slice(1), q1.slice(1)) + q0[0] * q1[0];
  const target = cosine < 0 ? q1.map((c) => -c) : q1;
  cosine = Math.abs(cosine);
  if (cosine > 0.9995) return normalize4(q0.map((c, i) => c + f * (target[i] - c)));
  const angle = Math.acos(cosine), sine = Math.sin(angle);
  const a = Math.sin((1 - f) * angle) / sine, b = Math.sin(f * angle) / sine;
  return q0.map((c, i) => a * c + b * target[i]);
}

function normalize4(q) {
  const n = Math.hypot(...q) || 1;
  return q.map((c) => c / n);
}

// Angle of `point` around the axis through `target` orthogonal to the plane (a, b), in (-pi, pi].
function azimuthOf(point, target, a, b) {
  const d = sub(point, target);
  return Math.atan2(dot(d, b), dot(d, a));
}

// An orthonormal pair (a, b) spanning the plane orthogonal to unit `up`, with a x b = up.
export function planeAxes(up) {
  const a = normalize(cross(up, Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]));
  return [a, cross(up, a)];
}

// The registered cameras in capture order along their arc around the scene: sorted by their angle about
// `up` through `target`, cut open at the widest gap (so the path never crosses where no photo was taken),
// closed into a ring when the cameras surround the scene, and oriented so that moving forward along the
// path moves the camera to its right. Returns {stops: [{image, centre, rotation (quaternion)}], closed}.
export function cameraPath(cameras, { target, up }) {
  const [a, b] = planeAxes(normalize(up));
  const stops = cameras.map((camera) => {
    const c2w = cameraToWorld(camera);
    return { image: camera.image, centre: [...camera.C], rotation: quaternionOf(c2w),
             right: [c2w[0][0], c2w[1][0], c2w[2][0]], angle: azimuthOf(camera.C, target, a, b) };
  }).sort((p, q) => p.angle - q.angle);
  const n = stops.length;
  let widest = -1, gap = 0;
  for (let i = 0; i < n; i++) {
    const next = i + 1 < n ? stops[i + 1].angle : stops[0].angle + 2 * Math.PI;
    if (next - stops[i].angle > gap) { gap = next - stops[i].angle; widest = i; }
  }
  const ordered = n ? stops.slice(widest + 1).concat(stops.slice(0, widest + 1)) : [];
  const closed = n >= MIN_RING_CAMERAS && gap < MAX_RING_GAP;
  let rightward = 0;
  for (let i = 0; i + 1 < n; i++) rightward += dot(sub(ordered[i + 1].centre, ordered[i].centre), ordered[i].right);
  if (rightward < 0) ordered.reverse();
  return { stops: ordered.map(({ image, centre, rotation }) => ({ image, centre, rotation })), closed };
}

// Where a path position may go: [0, n - 1] on an open path; any value on a ring (wrapped).
export function clampPosition(path, position) {
  const n = path.stops.length;
  if (path.closed) return ((position % n) + n) % n;
  return Math.min(n - 1, Math.max(0, position));
}

// The pose at a path position: between stop i and the next, centres interpolated linearly and rotations
// spherically. Returns {c2w (4x4 OpenGL), nearest (the nearest stop's image)}.
export function poseAt(path, position) {
  const { stops, closed } = path, n = stops.length;
  const s = clampPosition(path, position);
  const i = Math.min(Math.floor(s), closed ? n - 1 : Math.max(n - 2, 0)), f = s - i;
  const from = stops[i], to = stops[(i + 1) % n] || from;
  const centre = from.centre.map((c, k) => c + f * (to.centre[k] - c));
  const rotation = rotationOf(slerp(from.rotation, to.rotation, f));
  const c2w = [0, 1, 2].map((k) => [...rotation[k], centre[k]]).concat([[0, 0, 0, 1]]);
  return { c2w, nearest: (f < 0.5 ? from : to).image };
}

// The position the view starts at: the middle of an open path (the photo that sees most of what the others
// see), the first stop of a ring.
export const startPosition = (path) => (path.closed ? 0 : Math.floor((path.stops.length - 1) / 2));

// The free orbit: eye at `radius` from `target`, azimuth about `up` and elevation above the plane across it.
export function orbitEye({ target, up, radius }, azimuth, elevation) {
  const [a, b] = planeAxes(up);
  return [0, 1, 2].map((i) => target[i] + radius * (Math.cos(elevation) * (Math.cos(azimuth) * a[i]
    + Math.sin(azimuth) * b[i]) + Math.sin(elevation) * up[i]));
}

// Inverse of orbitEye: the {azimuth, elevation, radius} of an eye seen from `target`.
export function orbitAngles({ target, up }, eye) {
  const [a, b] = planeAxes(up);
  const d = sub(eye, target), radius = Math.hypot(...d) || 1;
  return { azimuth: Math.atan2(dot(d, b), dot(d, a)), elevation: Math.asin(Math.max(-1, Math.min(1, dot(d, up) / radius))),
           radius };
}
