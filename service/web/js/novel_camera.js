// The novel view's camera and how a drag moves it. Pure: the page feeds it drags and sends what
// renderCamera() gives to POST /v1/nerf/{id}/render.
//
// By default the camera stays among the photos: it starts at a registered camera and a horizontal drag
// moves it along the path through the registered cameras (clamped to the captured span; around a ring when
// the photos surround the scene). "Free" mode orbits the scene's centre in azimuth and elevation, from
// wherever the camera is. Without registered cameras (a NeRF trained on an uploaded dataset) only the free
// orbit exists, starting at azimuth 0 and elevation FREE_START_ELEVATION.
import { cameraPath, clampPosition, orbitAngles, orbitEye, poseAt, startPosition } from "./camera_path.js";
import { degrees } from "./format.js";

const ORBIT_RADIANS_PER_PX = 0.01;
const ELEVATION_LIMIT = 1.4; // radians: the free orbit never reaches the poles, where "up" degenerates
const FREE_START_ELEVATION = 0.3;

// config: the NeRF's config.json (orbit in the scene frame, normalization to the original frame).
// cameras: the registered cameras ({image, R, C}) in the original frame, possibly none.
export function createNovelCamera(config, cameras) {
  const { orbit, normalization } = config;
  const scale = normalization?.scale ?? 1, centre = normalization?.centre ?? [0, 0, 0];
  const frame = { target: orbit.target.map((v, i) => v / scale + centre[i]), up: orbit.up, radius: orbit.radius / scale };
  const path = cameras.length ? cameraPath(cameras, frame) : null;
  let free = !path, position = path ? startPosition(path) : 0;
  let angles = { azimuth: 0, elevation: FREE_START_ELEVATION, radius: frame.radius };

  return {
    get free() { return free; },
    get canFollowPath() { return path !== null; },
    get position() { return position; },

    // Switches mode; the free orbit starts where the camera is. Returns whether the view changed.
    setFree(wanted) {
      if (!path || wanted === free) return false;
      if (wanted) {
        const eye = poseAt(path, position).c2w.map((row) => row[3]);
        angles = orbitAngles(frame, eye);
        angles.elevation = Math.max(-ELEVATION_LIMIT, Math.min(ELEVATION_LIMIT, angles.elevation));
      }
      free = wanted;
      return true;
    },

    // A drag of (dx, dy) pixels on an image widthPx wide; returns whether the camera moved. Dragging right
    // pulls the scene right: the camera moves left. Across the image's width the path runs its whole span
    // (half the ring when closed).
    drag(dx, dy, widthPx) {
      if (free) {
        const before = angles;
        angles = { ...angles, azimuth: angles.azimuth - dx * ORBIT_RADIANS_PER_PX,
                   elevation: Math.max(-ELEVATION_LIMIT, Math.min(ELEVATION_LIMIT, angles.elevation + dy * ORBIT_RADIANS_PER_PX)) };
        return angles.azimuth !== before.azimuth || angles.elevation !== before.elevation;
      }
      const n = path.stops.length, span = path.closed ? n / 2 : n - 1;
      const next = clampPosition(path, position - (dx * span) / Math.max(widthPx, 1));
      const moved = next !== position;
      position = next;
      return moved;
    },

    // The camera of a render request, in the dataset's own frame ("data": the registered cameras' frame, not
    // the capture frame a photo scene's request is read in by default): {c2w} (OpenGL camera-to-world) on
    // the path; {eye, look_at, up} free, where a view that sees nothing of the scene is shown, not refused.
    renderCamera() {
      if (!free) return { c2w: poseAt(path, position).c2w, frame: "data" };
      return { eye: orbitEye({ ...frame, radius: angles.radius }, angles.azimuth, angles.elevation),
               look_at: frame.target, up: frame.up, frame: "data", allow_empty_view: true };
    },

    describe() {
      if (free) return `free orbit: azimuth ${degrees(angles.azimuth)}, elevation ${degrees(angles.elevation)}`;
      const n = path.stops.length, nearest = poseAt(path, position).nearest;
      const index = path.stops.findIndex((stop) => stop.image === nearest);
      return `near photo ${nearest} (${index + 1} of ${n} along the ${path.closed ? "ring" : "path"} of registered cameras)`;
    },
  };
}
