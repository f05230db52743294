"""Synthetic SfM scenes with known cameras and points: the ground truth for tests and benchmarks.

Cameras sit on an arc (a full ring when there are many) of radius about 6 around the world origin,
each looking at it with a little random elevation, roll and distance jitter. Points are uniform in
the cube [-2, 2]^3, kept only where every camera sees them (in front, inside the image), so they fill
the central part of every image. `render_box_ring` renders images instead: a box whose opposite sides look
alike, seen from a ring.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from estimation.geometry.projection import Camera
from estimation.geometry.projection import project as project_with_camera
from estimation.types import CameraPose, Tracks

SCENE_HALF_SIZE = 2.0
"""Points are drawn uniformly from [-SCENE_HALF_SIZE, SCENE_HALF_SIZE]^3, kept if every camera sees them."""
IMAGE_MARGIN_PX = 10.0
MIN_DEPTH = 1.0
CAMERA_DISTANCE = 6.0
"""Mean distance of a camera centre from the origin."""
ARC_STEP_DEG = 15.0
"""Azimuth between neighbouring cameras while the arc stays below a full ring."""


@dataclass(frozen=True)
class SyntheticScene:
    """Ground-truth cameras and points, and the (noisy, outlier-contaminated) tracks they produce."""

    K: np.ndarray                  # (3, 3)
    camera: Camera                 # the true intrinsics (K and distortion) of every image
    width: int
    height: int
    poses: list[CameraPose]        # world-to-camera, one per image
    points: np.ndarray             # (N, 3) world points; track t observes points[t]
    colors: np.ndarray             # (N, 3) uint8
    tracks: Tracks
    inlier_mask: np.ndarray        # (O,) bool: observation o is a (noisy) projection, not a random pixel

    @property
    def scene_size(self) -> float:
        """Diagonal of the bounding box of the points and camera centres (the '% of scene size' unit)."""
        everything = np.vstack([self.points, np.array([p.center for p in self.poses])])
        return float(np.linalg.norm(everything.max(axis=0) - everything.min(axis=0)))


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera R whose rows are the camera's x (right), y (down), z (forward) axes in world."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)          # with OpenCV's y pointing down, "up" = -y
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues: R = I + sin(a) [k]x + (1 - cos(a)) [k]x^2 for the unit axis k."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * kx + (1 - np.cos(angle_rad)) * kx @ kx


def project(camera: Camera | np.ndarray, pose: CameraPose, points: np.ndarray) -> np.ndarray:
    """Pixel projection of points (N, 3) -> (N, 2) by a Camera (or 3x3 K): u ~ K distort(R X + t)."""
    return project_with_camera(camera, pose.R, pose.t, points).uv


def _camera_poses(num_cameras: int, rng: np.random.Generator, arc_step_deg: float = ARC_STEP_DEG
                  ) -> list[CameraPose]:
    full_ring = arc_step_deg * num_cameras >= 360.0
    span_deg = 360.0 * (num_cameras - 1) / num_cameras if full_ring else arc_step_deg * (num_cameras - 1)
    azimuths = np.deg2rad(np.linspace(-span_deg / 2, span_deg / 2, num_cameras))
    world_up = np.array([0.0, -1.0, 0.0])     # the world uses OpenCV-like axes: y points down
    poses = []
    for azimuth in azimuths:
        elevation = np.deg2rad(rng.uniform(-10, 10))
        distance = CAMERA_DISTANCE * rng.uniform(0.9, 1.1)
        center = distance * np.array(
            [np.sin(azimuth) * np.cos(elevation), -np.sin(elevation), -np.cos(azimuth) * np.cos(elevation)]
        )
        R = look_at(center, rng.normal(0, 0.1, 3), world_up)
        R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.deg2rad(rng.uniform(-5, 5))) @ R
        poses.append(CameraPose.from_center(R, center))
    return poses


def _points_inside_all_images(camera: Camera, poses: list[CameraPose], width: int, height: int,
                              num_points: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform points in the cube, rejected unless in front of and inside the image of every camera."""
    kept = np.empty((0, 3))
    while len(kept) < num_points:
        candidates = rng.uniform(-SCENE_HALF_SIZE, SCENE_HALF_SIZE, (2 * num_points, 3))
        ok = np.ones(len(candidates), bool)
        for pose in poses:
            uv = project(camera, pose, candidates)
            ok &= (candidates @ pose.R.T + pose.t)[:, 2] > MIN_DEPTH
            ok &= (uv >= IMAGE_MARGIN_PX).all(axis=1)
            ok &= (uv[:, 0] < width - IMAGE_MARGIN_PX) & (uv[:, 1] < height - IMAGE_MARGIN_PX)
        kept = np.vstack([kept, candidates[ok]])
    return kept[:num_points]


def _visible_mask(num_points: int, num_cameras: int, visibility: float, rng: np.random.Generator
                  ) -> np.ndarray:
    """(N, M) bool: which camera sees which point; every point keeps at least two cameras."""
    visible = rng.random((num_points, num_cameras)) < visibility
    for n in np.flatnonzero(visible.sum(axis=1) < 2):
        visible[n, rng.choice(num_cameras, size=2, replace=False)] = True
    return visible


def observe(camera: Camera | np.ndarray, poses: list[CameraPose], points: np.ndarray, colors: np.ndarray,
            visible: np.ndarray, noise_px: float, outlier_fraction: float, image_size: tuple[int, int],
            rng: np.random.Generator) -> tuple[Tracks, np.ndarray]:
    """Tracks of `points` seen where `visible` (N, M): uv = pi(camera, R X + t) + N(0, noise_px^2), and a
    fraction of all observations replaced by uniform random pixels. Returns (tracks, inlier_mask (O,))."""
    track_index, image_index = np.nonzero(visible)          # sorted by track, then image
    uv_all = np.stack([project(camera, pose, points) for pose in poses], axis=1)   # (N, M, 2)
    uv = uv_all[track_index, image_index] + rng.normal(0.0, noise_px, (track_index.size, 2))
    inlier_mask = np.ones(track_index.size, bool)
    outliers = rng.choice(track_index.size, size=round(outlier_fraction * track_index.size), replace=False)
    inlier_mask[outliers] = False
    uv[outliers] = rng.uniform([0.0, 0.0], image_size, (outliers.size, 2))
    tracks = Tracks(
        image_names=[f"{m + 1}.png" for m in range(len(poses))],
        track_index=track_index.astype(np.int64),
        image_index=image_index.astype(np.int64),
        uv=uv,
        colors=colors,
    )
    return tracks, inlier_mask


def make_scene(
    num_cameras: int = 5,
    num_points: int = 500,
    noise_px: float = 0.0,
    outlier_fraction: float = 0.0,
    seed: int = 0,
    width: int = 800,
    height: int = 600,
    visibility: float = 1.0,
    camera: Camera | None = None,
    arc_step_deg: float = ARC_STEP_DEG,
) -> SyntheticScene:
    """A scene with known poses and points; tracks are projections + N(0, noise_px^2) pixel noise.

    `outlier_fraction` of all observations are replaced by uniformly random pixels (so a pair of
    images shares a fraction 1 - (1 - f)^2 of wrong matches). `visibility` < 1 drops each observation
    with probability 1 - visibility, keeping at least two per track. `camera` (default: pinhole, focal
    0.75 width, principal point at the centre) may add distortion or move the principal point.
    `arc_step_deg` is the azimuth between neighbouring cameras (a façade capture turns a few degrees).
    """
    if num_cameras < 2:
        raise ValueError(f"make_scene needs at least 2 cameras, got {num_cameras}")
    if not 0.0 <= outlier_fraction < 1.0:
        raise ValueError(f"outlier_fraction must be in [0, 1), got {outlier_fraction}")
    if not 0.0 < visibility <= 1.0:
        raise ValueError(f"visibility must be in (0, 1], got {visibility}")
    rng = np.random.default_rng(seed)
    if camera is None:
        focal = 0.75 * width
        camera = Camera("pinhole", fx=focal, fy=focal, cx=width / 2, cy=height / 2)
    poses = _camera_poses(num_cameras, rng, arc_step_deg)
    points = _points_inside_all_images(camera, poses, width, height, num_points, rng)
    colors = rng.integers(0, 256, (num_points, 3), dtype=np.uint8)

    visible = _visible_mask(num_points, num_cameras, visibility, rng)
    tracks, inlier_mask = observe(camera, poses, points, colors, visible, noise_px, outlier_fraction,
                                  (width, height), rng)
    return SyntheticScene(K=camera.K, camera=camera, width=width, height=height, poses=poses, points=points,
                          colors=colors, tracks=tracks, inlier_mask=inlier_mask)


OBJECT_RADIUS = 1.5
"""Object scenes: points lie on a sphere of this radius around the origin."""
MAX_VIEWING_ANGLE_DEG = 70.0
"""A surface point is seen by a camera when its normal is within this angle of the direction to the camera
(the far side of the object is hidden), as in a capture around an object."""


def _object_camera_poses(num_cameras: int, layout: str, rng: np.random.Generator) -> list[CameraPose]:
    """Cameras looking at the origin: a ring (elevation about 15 deg) or a hemisphere (10..70 deg rings)."""
    if layout == "ring":
        elevations = np.full(num_cameras, 15.0)
        azimuths = np.linspace(0.0, 360.0, num_cameras, endpoint=False)
    elif layout == "hemisphere":
        rings = max(2, round(np.sqrt(num_cameras / 3)))
        per_ring = np.array_split(np.arange(num_cameras), rings)
        ring_elevations = np.linspace(10, 70, rings)
        elevations = np.concatenate([np.full(len(r), e)
                                     for r, e in zip(per_ring, ring_elevations, strict=True)])
        azimuths = np.concatenate([np.linspace(0.0, 360.0, len(r), endpoint=False) + 17.0 * k
                                   for k, r in enumerate(per_ring)])
    else:
        raise ValueError(f"layout must be 'ring' or 'hemisphere', got {layout!r}")
    world_up = np.array([0.0, -1.0, 0.0])
    poses = []
    jittered = np.radians(elevations + rng.uniform(-3, 3, num_cameras))
    for azimuth, elevation in zip(np.radians(azimuths), jittered, strict=True):
        distance = CAMERA_DISTANCE * rng.uniform(0.9, 1.1)
        center = distance * np.array([np.sin(azimuth) * np.cos(elevation), -np.sin(elevation),
                                      -np.cos(azimuth) * np.cos(elevation)])
        R = look_at(center, rng.normal(0, 0.1, 3), world_up)
        R = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.deg2rad(rng.uniform(-5, 5))) @ R
        poses.append(CameraPose.from_center(R, center))
    return poses


def make_object_scene(
    num_cameras: int = 24,
    layout: str = "ring",
    num_points: int = 2000,
    noise_px: float = 0.0,
    outlier_fraction: float = 0.0,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    shuffle: bool = False,
) -> SyntheticScene:
    """Photos around an object: points on a sphere, each seen only by the cameras facing its side.

    `layout` "ring" or "hemisphere"; `shuffle` puts the images in random file order (image m is no longer
    next to images m - 1 and m + 1), as unordered captures are. Noise and outliers as in `make_scene`.
    """
    rng = np.random.default_rng(seed)
    focal = 0.9 * width
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    poses = _object_camera_poses(num_cameras, layout, rng)
    if shuffle:
        poses = [poses[m] for m in rng.permutation(num_cameras)]
    # Upper part of the sphere only for a hemisphere capture (the object stands on the ground).
    normals = rng.normal(size=(4 * num_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    if layout == "hemisphere":
        normals = normals[normals[:, 1] < 0.2]
    normals = normals[:num_points]
    points = OBJECT_RADIUS * normals
    centers = np.array([pose.center for pose in poses])
    to_camera = centers[None, :, :] - points[:, None, :]
    cosine = np.einsum("nmk,nk->nm", to_camera, normals) / np.linalg.norm(to_camera, axis=2)
    visible = cosine > np.cos(np.radians(MAX_VIEWING_ANGLE_DEG))
    for m, pose in enumerate(poses):
        uv = project(K, pose, points)
        visible[:, m] &= (uv >= IMAGE_MARGIN_PX).all(axis=1) & (uv[:, 0] < width - IMAGE_MARGIN_PX) & (
            uv[:, 1] < height - IMAGE_MARGIN_PX)
    keep = visible.sum(axis=1) >= 2
    points, visible = points[keep], visible[keep]
    colors = rng.integers(0, 256, (len(points), 3), dtype=np.uint8)
    tracks, inlier_mask = observe(K, poses, points, colors, visible, noise_px, outlier_fraction,
                                  (width, height), rng)
    return SyntheticScene(K=K, camera=Camera.from_K(K), width=width, height=height, poses=poses,
                          points=points, colors=colors, tracks=tracks, inlier_mask=inlier_mask)


@dataclass(frozen=True)
class SymmetricRing:
    """A ring around an object symmetric under a half turn about the vertical axis, with images whose
    matcher took look-alike features of the far side for their own."""

    scene: SyntheticScene
    confused: tuple[int, ...]          # images with symmetric mismatches
    half_turn: np.ndarray              # (3, 3) the object's symmetry (about the world's vertical axis)


def make_symmetric_ring(num_cameras: int = 24, num_points: int = 3000, confused: tuple[int, ...] = (5,),
                        confusion: float = 0.6, noise_px: float = 0.3, seed: int = 0) -> SymmetricRing:
    """Cameras on a ring (`make_object_scene`) around points on a sphere that come in symmetric pairs X and
    H X (H: a half turn about the vertical axis, so the far side looks like the near one). In each confused
    image, a `confusion` share of its observations is linked to the track of the symmetric point instead,
    as a matcher links look-alike features: the image then carries a complete, consistent second placement,
    its true pose turned by H, which every track of those observations supports."""
    rng = np.random.default_rng(seed)
    base = make_object_scene(num_cameras, "ring", num_points // 2, seed=seed)
    half_turn = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.pi)
    half = len(base.points)
    normals = base.points / OBJECT_RADIUS
    points = np.vstack([base.points, base.points @ half_turn.T])
    colors = np.vstack([base.colors, base.colors])
    all_normals = np.vstack([normals, normals @ half_turn.T])
    centers = np.array([pose.center for pose in base.poses])
    to_camera = centers[None, :, :] - points[:, None, :]
    cosine = np.einsum("nmk,nk->nm", to_camera, all_normals) / np.linalg.norm(to_camera, axis=2)
    visible = cosine > np.cos(np.radians(MAX_VIEWING_ANGLE_DEG))
    for m, pose in enumerate(base.poses):
        uv = project(base.K, pose, points)
        visible[:, m] &= (uv >= IMAGE_MARGIN_PX).all(axis=1) & (uv[:, 0] < base.width - IMAGE_MARGIN_PX) & (
            uv[:, 1] < base.height - IMAGE_MARGIN_PX)
    tracks, inlier_mask = observe(base.K, base.poses, points, colors, visible, noise_px, 0.0,
                                  (base.width, base.height), rng)
    track_index = tracks.track_index.copy()
    twin = np.concatenate([np.arange(half, 2 * half), np.arange(half)])   # point n <-> its symmetric one
    for m in confused:
        own = np.flatnonzero(tracks.image_index == m)
        swap = own[rng.random(len(own)) < confusion]
        # A track holds one observation per image: the twin must not be seen in m already.
        swap = swap[~visible[twin[track_index[swap]], m]]
        track_index[swap] = twin[track_index[swap]]
    scene = SyntheticScene(K=base.K, camera=base.camera, width=base.width, height=base.height,
                           poses=base.poses, points=points, colors=colors,
                           tracks=Tracks(tracks.image_names, track_index, tracks.image_index, tracks.uv,
                                         colors),
                           inlier_mask=inlier_mask)
    return SymmetricRing(scene, tuple(confused), half_turn)


BOX_HALF_SIZE = np.array([1.0, 0.6, 0.7])
"""Half the rendered box's extent along the world's x, y and z (up); it stands on the ground plane."""
TEXTURE_SIZE = 512
GROUND_TILE = 6.0
"""World units covered by one copy of the ground's texture (tiled)."""
SUPERSAMPLING = 2
"""Rays per pixel side (the image is the mean of SUPERSAMPLING^2 rays: edges anti-aliased)."""
BACKGROUND_GREY = 200.0
MIN_RING_VIEWS = 3
MIN_RENDER_SIZE = 16


@dataclass(frozen=True)
class RenderedRing:
    """Rendered RGB images (uint8) with their true cameras (world-to-camera, OpenCV axes)."""

    images: list[np.ndarray]
    poses: list[CameraPose]
    K: np.ndarray


def _with_marks(texture: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """The texture with `count` random filled discs, rectangles and letters drawn on it."""
    texture = texture.copy()
    size = texture.shape[0]
    for _ in range(count):
        colour = tuple(int(v) for v in rng.integers(0, 256, 3))
        corner = tuple(int(v) for v in rng.integers(0, size, 2))
        extent = int(rng.integers(10, 50))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(texture, corner, extent, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            opposite = (corner[0] + extent, corner[1] + int(rng.integers(10, 50)))
            cv2.rectangle(texture, corner, opposite, colour, -1, cv2.LINE_AA)
        else:
            letter = chr(int(rng.integers(65, 91)))
            cv2.putText(texture, letter, corner, cv2.FONT_HERSHEY_SIMPLEX, extent / 15, colour, 3,
                        cv2.LINE_AA)
    return texture


def _pattern(rng: np.random.Generator, marks: int) -> np.ndarray:
    """A TEXTURE_SIZE^2 RGB texture: coloured noise at three scales under `marks` random shapes."""
    noise = np.zeros((TEXTURE_SIZE, TEXTURE_SIZE, 3), np.float32)
    for cell in (4, 16, 64):
        coarse = rng.random((TEXTURE_SIZE // cell + 1, TEXTURE_SIZE // cell + 1, 3)).astype(np.float32)
        noise += cv2.resize(coarse, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_CUBIC) * cell**-0.3
    noise = (noise - noise.min()) / (noise.max() - noise.min()) * 160.0 + 40.0
    return _with_marks(noise.astype(np.uint8), rng, marks)


def _sample(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear texture colours at u, v in [0, 1] (rows of 1024: OpenCV's remap takes < 32767 per side)."""
    count, row = len(u), 1024
    if count == 0:
        return np.zeros((0, 3), np.float32)
    pad = (-count) % row
    side = texture.shape[0] - 1
    map_u = np.pad(u * side, (0, pad)).astype(np.float32).reshape(-1, row)
    map_v = np.pad(v * side, (0, pad)).astype(np.float32).reshape(-1, row)
    return cv2.remap(texture, map_u, map_v, cv2.INTER_LINEAR).reshape(-1, 3)[:count].astype(np.float32)


def _render_box(K: np.ndarray, pose: CameraPose, size: int, sides: dict, ground: np.ndarray | None,
                light: np.ndarray) -> np.ndarray:
    """Ray-cast the box (slab test) and the ground plane z = -BOX_HALF_SIZE[2] from one camera."""
    pixels = (np.arange(size * SUPERSAMPLING) + 0.5) / SUPERSAMPLING - 0.5
    u, v = np.meshgrid(pixels, pixels)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ pose.R
    origin = pose.center
    with np.errstate(divide="ignore", invalid="ignore"):
        near, far = (-BOX_HALF_SIZE - origin) / rays, (BOX_HALF_SIZE - origin) / rays
    entry = np.nanmax(np.minimum(near, far), -1)
    hit = (np.nanmin(np.maximum(near, far), -1) >= entry) & (entry > 0)
    image = np.full(u.shape + (3,), BACKGROUND_GREY, np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        to_ground = (-BOX_HALF_SIZE[2] - origin[2]) / rays[..., 2]
    on_ground = (to_ground > 0) & ~hit
    if ground is not None:
        spot = origin[:2] + to_ground[on_ground][:, None] * rays[on_ground][:, :2]
        tile = np.mod(spot / GROUND_TILE, 1.0)
        image[on_ground] = _sample(ground, tile[:, 0], tile[:, 1])
    surface = origin + entry[..., None] * rays
    for (axis, sign), texture in sides.items():
        on_side = hit & (np.abs(surface[..., axis] - sign * BOX_HALF_SIZE[axis]) < 1e-4)
        normal = np.zeros(3)
        normal[axis] = sign
        point = surface[on_side]
        if axis == 2:
            across, down = point[:, 0] / BOX_HALF_SIZE[0], point[:, 1] / BOX_HALF_SIZE[1]
        else:
            # u along the side as seen from outside: opposite sides map alike under a half turn about z
            right = np.cross([0.0, 0.0, 1.0], normal)
            across, down = point @ right / BOX_HALF_SIZE[1 - axis], -point[:, 2] / BOX_HALF_SIZE[2]
        shade = 0.55 + 0.45 * max(0.0, float(normal @ light))
        image[on_side] = shade * _sample(texture, (across + 1) / 2, (down + 1) / 2)
    return cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)


def render_box_ring(num_views: int = 36, size: int = 400, unique_marks: int = 8, textured_ground: bool = True,
                    noise_grey: float = 1.0, seed: int = 0) -> RenderedRing:
    """A box whose opposite sides carry one texture each (a half turn about the vertical maps the box onto
    itself, but for `unique_marks` marks of each side and the top's own texture), on a ground plane (tiled
    random marks, or plain grey), lit from one side, seen from `num_views` cameras on a ring around it
    (equal azimuth steps with 1 deg of jitter, 25 +- 5 deg elevation, 4.2 +- 0.15 from its centre, 65 deg
    field of view), with Gaussian sensor noise: views half a turn apart look alike."""
    if num_views < MIN_RING_VIEWS:
        raise ValueError(f"render_box_ring: num_views must be at least {MIN_RING_VIEWS}, got {num_views}")
    if size < MIN_RENDER_SIZE:
        raise ValueError(f"render_box_ring: size must be at least {MIN_RENDER_SIZE} px, got {size}")
    rng = np.random.default_rng(seed)
    front, side = _pattern(rng, 60), _pattern(rng, 60)
    sides = {(0, 1): _with_marks(front, rng, unique_marks), (0, -1): _with_marks(front, rng, unique_marks),
             (1, 1): _with_marks(side, rng, unique_marks), (1, -1): _with_marks(side, rng, unique_marks),
             (2, 1): _pattern(rng, 60)}
    ground = None
    if textured_ground:
        blank = np.full((2 * TEXTURE_SIZE, 2 * TEXTURE_SIZE, 3), 190, np.uint8)
        ground = (_with_marks(blank, rng, 150) * 0.5 + 100).astype(np.uint8)
    focal = 0.78 * size
    K = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    light = np.array([0.5, 0.3, 0.8]) / np.linalg.norm([0.5, 0.3, 0.8])
    images, poses = [], []
    for k in range(num_views):
        azimuth = 2 * np.pi * k / num_views + np.radians(rng.normal(0.0, 1.0))
        elevation = np.radians(25.0 + rng.normal(0.0, 5.0))
        distance = 4.2 + rng.normal(0.0, 0.15)
        centre = distance * np.array([np.cos(elevation) * np.cos(azimuth),
                                      np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        R = look_at(centre, rng.normal(0.0, 0.05, 3), np.array([0.0, 0.0, 1.0]))
        pose = CameraPose(R=R, t=-R @ centre)
        rgb = _render_box(K, pose, size, sides, ground, light) + rng.normal(0.0, noise_grey, (size, size, 3))
        images.append(np.clip(np.rint(rgb), 0, 255).astype(np.uint8))
        poses.append(pose)
    return RenderedRing(images, poses, K)
