// The 3D view of a reconstruction: coloured points and camera frusta (coloured by registration order),
// orbit and zoom with three.js's OrbitControls. Cameras are world-to-camera R, t (OpenCV axes: x right,
// y down, z forward) with centre C = -R^T t, as GET /v1/reconstructions/{id} gives them.
import * as THREE from "../vendor/three/three.module.min.js";
import { OrbitControls } from "../vendor/three/OrbitControls.js";
import { orderColour } from "./colours.js";

const FRUSTUM_DEPTH_FRACTION = 0.12; // frustum depth as a fraction of the scene radius
const POINT_SIZE_PX = 2.5;

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted.length ? sorted[Math.floor(sorted.length / 2)] : 0;
}

// Renders into `container`; returns {dispose}. container gets data-cameras, data-points, data-ready="true".
export function showReconstruction(container, { points, cameras, intrinsics, registrationOrder }) {
  container.replaceChildren();
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  container.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x10131a);

  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(points.positions, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(points.colors, 3, true));
  scene.add(new THREE.Points(geometry, new THREE.PointsMaterial({
    size: POINT_SIZE_PX, sizeAttenuation: false, vertexColors: true })));

  // Scene centre: the median point (robust to far outliers); radius: median distance to it.
  const p = points.positions;
  const centre = new THREE.Vector3(
    median(Array.from({ length: points.count }, (_, i) => p[3 * i])),
    median(Array.from({ length: points.count }, (_, i) => p[3 * i + 1])),
    median(Array.from({ length: points.count }, (_, i) => p[3 * i + 2])));
  const centres = cameras.map((c) => new THREE.Vector3(...c.C));
  const radius = median([
    ...Array.from({ length: points.count }, (_, i) => centre.distanceTo(new THREE.Vector3(p[3 * i], p[3 * i + 1], p[3 * i + 2]))),
    ...centres.map((c) => c.distanceTo(centre)),
  ]) || 1;

  // Frusta: the camera centre and the four image corners at depth d, back-projected into the world.
  const order = new Map(registrationOrder.map((name, i) => [name, i]));
  const depth = FRUSTUM_DEPTH_FRACTION * radius;
  const { K, width, height } = intrinsics;
  const vertices = [], vertexColors = [];
  const up = new THREE.Vector3();
  for (const camera of cameras) {
    const R = camera.R, C = new THREE.Vector3(...camera.C);
    const toWorld = (x, y, z) => new THREE.Vector3(   // C + R^T [x y z]
      C.x + R[0][0] * x + R[1][0] * y + R[2][0] * z,
      C.y + R[0][1] * x + R[1][1] * y + R[2][1] * z,
      C.z + R[0][2] * x + R[1][2] * y + R[2][2] * z);
    up.add(new THREE.Vector3(-R[1][0], -R[1][1], -R[1][2])); // camera "up" is -y in OpenCV axes
    const corners = [[0, 0], [width, 0], [width, height], [0, height]].map(([u, v]) =>
      toWorld(((u - K[0][2]) / K[0][0]) * depth, ((v - K[1][2]) / K[1][1]) * depth, depth));
    const colour = new THREE.Color(...orderColour(order.get(camera.image) ?? 0, cameras.length));
    for (let k = 0; k < 4; k++) {
      for (const v of [C, corners[k], corners[k], corners[(k + 1) % 4]]) {
        vertices.push(v.x, v.y, v.z);
        vertexColors.push(colour.r, colour.g, colour.b);
      }
    }
  }
  const lines = new THREE.BufferGeometry();
  lines.setAttribute("position", new THREE.Float32BufferAttribute(vertices, 3));
  lines.setAttribute("color", new THREE.Float32BufferAttribute(vertexColors, 3));
  scene.add(new THREE.LineSegments(lines, new THREE.LineBasicMaterial({ vertexColors: true })));

  const view = new THREE.PerspectiveCamera(50, 1, radius / 1000, radius * 100);
  view.up.copy(up.lengthSq() > 0 ? up.normalize() : new THREE.Vector3(0, -1, 0));
  const meanCentre = centres.reduce((a, c) => a.add(c), new THREE.Vector3()).divideScalar(Math.max(centres.length, 1));
  // Look at a point between the cameras and the scene from behind and above the cameras, so that both are in view.
  const target = centre.clone().lerp(meanCentre, 0.4);
  const back = meanCentre.clone().sub(centre);
  const distance = Math.max(back.length() * 1.5, radius * 1.6);
  if (back.lengthSq() === 0) back.set(0, 0, -1);
  view.position.copy(target).add(back.setLength(distance)).add(view.up.clone().multiplyScalar(distance * 0.6));
  const controls = new OrbitControls(view, renderer.domElement);
  controls.target.copy(target);
  controls.update();

  const draw = () => renderer.render(scene, view);
  const resize = () => {
    const w = container.clientWidth || 640, h = container.clientHeight || 420;
    renderer.setSize(w, h, false);
    view.aspect = w / h;
    view.updateProjectionMatrix();
    draw();
  };
  controls.addEventListener("change", draw);
  const observer = new ResizeObserver(resize);
  observer.observe(container);
  resize();

  const legend = document.createElement("div");
  legend.className = "legend";
  legend.textContent = `${cameras.length} cameras (red = first registered … blue = last), ${points.count} points — drag to orbit, wheel to zoom`;
  container.appendChild(legend);
  container.dataset.cameras = String(cameras.length);
  container.dataset.points = String(points.count);
  container.dataset.ready = "true";
  performance.mark("sfmnerf:view3d-ready"); // drawn, controls attached: benchmarks read it as interactive
  return {
    dispose() {
      observer.disconnect();
      controls.dispose();
      renderer.dispose();
    },
  };
}
