"""Rendering trained runs: whole images in memory-bounded chunks, novel views, orbits.

A run's poses live in its scene frame; callers pass poses in the dataset's original frame (for Blender and
tiny-NeRF data the two coincide; a reconstruction's frame is re-centred and scaled, see
neural.bounds.SceneNormalization) or in the capture frame of its photos (neural.camera_path.capture_frame),
or no pose for the default view (a registered camera), and this module converts them, once.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from neural.artefacts import RUN_CONFIG_FILE
from neural.bounds import Bounds, SceneNormalization
from neural.camera_path import (
    CameraPathError,
    Capture,
    capture_frame,
    detect_capture,
    path_poses,
    pose_from_capture_frame,
)
from neural.checkpoints import load_model_state, load_named_checkpoint
from neural.config import TrainConfig
from neural.environment import Background, Environment, background_for
from neural.errors import CheckpointError
from neural.models import RadianceModel, build_model
from neural.rays import generate_rays
from neural.video import write_video

#: Orbit cameras sit this many degrees above the plane normal to the mean training "up".
DEFAULT_ORBIT_ELEVATION_DEG = 30.0
#: A pixel sees the scene when its accumulated opacity reaches EMPTY_VIEW_OPACITY; a view where fewer than
#: EMPTY_VIEW_FRACTION of the pixels do sees nothing (Herz-Jesus-P8 seen from the data frame's eye
#: [0,-4,1]: a black haze of opacity <= 0.06 everywhere; a photo's view: >= 0.99 everywhere).
EMPTY_VIEW_OPACITY = 0.5
EMPTY_VIEW_FRACTION = 0.01
#: How a requested pose is read: "capture" (photo scenes: the frame of neural.camera_path.capture_frame,
#: origin at what the photos look at, z up, the default camera at (0, -4, *)), "data" (the dataset's own
#: frame) or "auto" (capture for photo scenes, data otherwise).
PoseFrame = Literal["auto", "capture", "data"]
#: The video's camera path: "captured" (through the registered cameras) or "orbit" (a circle round them).
VideoPath = Literal["captured", "orbit"]


class EmptyViewError(ValueError):
    """The view sees nothing of the scene: the camera looks away from it."""


class RenderedImage(NamedTuple):
    """rgb (H,W,3) in [0,1], depth (H,W) (distance along the ray, scene units), opacity (H,W)."""

    rgb: Tensor
    depth: Tensor
    opacity: Tensor


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Pinhole intrinsics in pixels for an image of width x height."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def downscaled(self, factor: int) -> PinholeIntrinsics:
        """The camera of factor x factor pixel blocks (the image cropped to whole blocks)."""
        f = float(factor)
        return PinholeIntrinsics(
            self.width // factor, self.height // factor, self.fx / f, self.fy / f, self.cx / f, self.cy / f
        )


@dataclass
class LoadedRun:
    """A trained model on its device with what is needed to render it."""

    model: RadianceModel
    config: TrainConfig
    scene: Bounds
    normalization: SceneNormalization
    camera: PinholeIntrinsics
    orbit: dict[str, Any]
    step: int
    device: torch.device
    background: Background
    cameras: np.ndarray | None = None
    """(N,4,4) the registered cameras' camera-to-world poses in the scene frame (None: an older run)."""
    photos: bool = False
    """Trained on photographs (a reconstruction): requests are read in the capture frame by default."""

    def capture(self) -> Capture:
        """How the photos were taken (neural.camera_path); CameraPathError without registered cameras."""
        if self.cameras is None:
            raise CameraPathError(
                "the run records no registered cameras (it was trained by an older version)"
            )
        return detect_capture(self.cameras)

    def default_pose(self) -> np.ndarray:
        """The default novel view (scene frame): the registered camera nearest the middle of the path."""
        return self.cameras[self.capture().default_index]

    def pose_to_scene(self, c2w: np.ndarray | None, frame: PoseFrame = "auto") -> np.ndarray:
        """A requested camera-to-world pose (None: the default view) in the scene frame."""
        if c2w is None:
            return self.default_pose()
        c2w = np.asarray(c2w, dtype=np.float64)
        if frame == "capture" or (frame == "auto" and self.photos and self.cameras is not None):
            return pose_from_capture_frame(c2w, capture_frame(self.cameras, self.capture()))
        return self.normalization.pose_to_scene(c2w)


def resolve_device(name: str) -> torch.device:
    """ "auto" -> cuda when available, else cpu; "cuda" without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but no CUDA GPU is available (use --device cpu or auto)")
    return torch.device(name)


def background_colour(background: str | None, device: torch.device) -> Tensor:
    """The colour renders are composited on: white, else black (also for runs trained on random colours)."""
    return torch.full((3,), 1.0 if background in (None, "white") else 0.0, device=device)


def stored_environment(payload: dict[str, Any]) -> Environment | None:
    """The photos' environment a checkpoint holds (None: a run without one, or written before it existed)."""
    values = payload.get("environment")
    return None if values is None else Environment.from_list(values)


def render_background(
    config: TrainConfig, environment: Environment | None, device: torch.device
) -> Background:
    """What a run's renders show behind the field: the photos' environment (neural.environment) for a run
    trained on random colours that fitted one and renders it, else its background colour."""
    if config.background == "random" and config.render_environment and environment is not None:
        return environment
    return background_colour(config.background, device)


@torch.no_grad()
def render_rays_chunked(
    model: RadianceModel,
    origins: Tensor,
    directions: Tensor,
    scene: Bounds,
    background: Background,
    chunk_rays: int,
) -> RenderedImage:
    """Render rays chunk_rays at a time (bounds memory: lower chunk_rays if you run out); flat outputs."""
    model.eval()
    rgb, depth, opacity = [], [], []
    for start in range(0, origins.shape[0], chunk_rays):
        chunk_directions = directions[start : start + chunk_rays]
        out = model.render_rays(
            origins[start : start + chunk_rays],
            chunk_directions,
            scene.near,
            scene.far,
            background_for(background, chunk_directions),
            train=False,
            generator=None,
        )
        rgb.append(out.rgb)
        depth.append(out.depth)
        opacity.append(out.opacity)
    return RenderedImage(torch.cat(rgb).clamp(0, 1), torch.cat(depth), torch.cat(opacity))


def render_image(
    model: RadianceModel,
    c2w_scene: Tensor,
    camera: PinholeIntrinsics,
    scene: Bounds,
    background: Background,
    chunk_rays: int,
) -> RenderedImage:
    """The (H,W) image of a camera with pose c2w_scene (OpenGL, the model's scene frame)."""
    rays = generate_rays(c2w_scene, camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy)
    flat = render_rays_chunked(model, rays.origins, rays.directions, scene, background, chunk_rays)
    shape = (camera.height, camera.width)
    return RenderedImage(flat.rgb.reshape(*shape, 3), flat.depth.reshape(shape), flat.opacity.reshape(shape))


def to_uint8(rgb: Tensor | np.ndarray) -> np.ndarray:
    array = rgb.detach().cpu().numpy() if isinstance(rgb, Tensor) else np.asarray(rgb)
    return (np.clip(array, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def depth_to_uint8(depth: Tensor, scene: Bounds) -> np.ndarray:
    """Depth as a grey (H,W,3) image, near bright: linear from [near, far] to [255, 0], or for an unbounded
    scene (far is very far) as disparity near / depth."""
    if scene.unbounded:
        scaled = scene.near / depth.clamp_min(scene.near)
    else:
        scaled = 1.0 - (depth - scene.near) / (scene.far - scene.near)
    grey = to_uint8(scaled.clamp(0, 1))
    return np.repeat(grey[..., None], 3, axis=-1)


def read_run_config(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / RUN_CONFIG_FILE
    if not path.is_file():
        raise CheckpointError(f"{run_dir}: not a training run (no {RUN_CONFIG_FILE})")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise CheckpointError(f"{path}: corrupt run config ({error})") from None


def load_run(run_dir: Path | str, checkpoint: str = "latest", device: str = "auto") -> LoadedRun:
    """The run's model restored from `checkpoint` ("latest", "best", a step or a .pt path)."""
    run_dir = Path(run_dir)
    info = read_run_config(run_dir)
    target = resolve_device(device)
    path, payload = load_named_checkpoint(run_dir, checkpoint, map_location=target)
    config = TrainConfig.model_validate(info["train"])
    if payload.get("model_name") != config.model:
        raise CheckpointError(
            f"{path}: checkpoint holds model {payload.get('model_name')!r} but {run_dir / RUN_CONFIG_FILE} "
            f"says {config.model!r}"
        )
    scene = Bounds.from_dict(info["scene"])
    model = build_model(config.model, scene, **payload["model_config"]).to(target)
    load_model_state(model, payload["model_state"], path)
    model.eval()
    return LoadedRun(
        model=model,
        config=config,
        scene=scene,
        normalization=SceneNormalization.from_dict(info["normalization"]),
        camera=PinholeIntrinsics(**info["camera"]),
        orbit=info["orbit"],
        step=int(payload["step"]),
        device=target,
        background=render_background(config, stored_environment(payload), target),
        cameras=np.asarray(info["cameras"]["c2w"], dtype=np.float64) if "cameras" in info else None,
        photos=bool(info.get("cameras", {}).get("photos", False)),
    )


def view_camera(
    run: LoadedRun, width: int, height: int, fx: float | None, fov_x: float | None
) -> PinholeIntrinsics:
    """Intrinsics for a requested view: fx given, else from the horizontal field of view, else the training
    camera's, scaled to the requested width; fy = fx (square pixels), principal point at the centre."""
    if fx is None and fov_x is not None:
        fx = 0.5 * width / math.tan(0.5 * fov_x)
    if fx is None:
        fx = run.camera.fx * width / run.camera.width
    return PinholeIntrinsics(width, height, fx, fx, width / 2.0, height / 2.0)


def render_frame(
    run: LoadedRun, c2w: np.ndarray | None, camera: PinholeIntrinsics, frame: PoseFrame = "data"
) -> RenderedImage:
    """Render a view whose camera-to-world pose (OpenGL) is given in `frame` (None: the default view)."""
    pose = torch.as_tensor(run.pose_to_scene(c2w, frame), dtype=torch.float32, device=run.device)
    return render_image(run.model, pose, camera, run.scene, run.background, run.config.chunk_rays)


def check_sees_scene(rendered: RenderedImage) -> RenderedImage:
    """The render, or EmptyViewError when almost no pixel sees the scene (the image is background or haze)."""
    seeing = float((rendered.opacity >= EMPTY_VIEW_OPACITY).float().mean())
    if seeing < EMPTY_VIEW_FRACTION:
        raise EmptyViewError(
            f"the view sees nothing of the scene ({100 * seeing:.1f} % of its pixels reach opacity "
            f"{EMPTY_VIEW_OPACITY}): the camera looks away from "
            "what the photos saw, or training has not filled the field yet; leave the camera out for a "
            "photo's view, or move it towards the cameras (GET .../camera-path lists them)"
        )
    return rendered


def render_view(
    run_dir: Path | str,
    c2w: np.ndarray | None,
    width: int,
    height: int,
    fx: float | None = None,
    fov_x: float | None = None,
    checkpoint: str = "latest",
    device: str = "auto",
    frame: PoseFrame = "data",
) -> np.ndarray:
    """(H,W,3) uint8 render of the camera c2w (4,4, OpenGL camera-to-world in `frame`; None: the default
    view); EmptyViewError when it sees nothing of the scene."""
    run = load_run(run_dir, checkpoint, device=device)
    return to_uint8(
        check_sees_scene(render_frame(run, c2w, view_camera(run, width, height, fx, fov_x), frame)).rgb
    )


def camera_path(run_dir: Path | str, num_frames: int) -> dict[str, Any]:
    """The run's capture (kind, span_deg, closed) with its default view, cameras in path order and a video
    path of num_frames poses, all camera-to-world in the dataset's original frame; reads config.json only.
    CameraPathError when the run records no registered cameras."""
    info = read_run_config(Path(run_dir))
    cameras = np.asarray(info.get("cameras", {}).get("c2w", []), dtype=np.float64)
    capture = detect_capture(cameras)
    to_data = SceneNormalization.from_dict(info["normalization"]).pose_to_original
    return {
        "kind": capture.kind,
        "span_deg": capture.span_deg,
        "closed": capture.closed,
        "default_view": to_data(cameras[capture.default_index]).tolist(),
        "cameras": to_data(cameras[capture.order]).tolist(),
        "path": to_data(path_poses(cameras, capture, num_frames)).tolist(),
    }


def orbit_parameters(poses_scene: np.ndarray) -> dict[str, Any]:
    """Centre (the point nearest all optical axes), radius, up of the training cameras, for orbits."""
    centres = poses_scene[:, :3, 3]
    forwards = -poses_scene[:, :3, 2]
    # least squares point closest to every optical axis: sum (I - f f^T) (x - c) = 0
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]
    lhs, rhs = projectors.sum(0), np.einsum("nij,nj->i", projectors, centres)
    target = np.linalg.lstsq(lhs, rhs, rcond=None)[0] if np.linalg.matrix_rank(lhs) == 3 else centres.mean(0)
    up = poses_scene[:, :3, 1].mean(axis=0)
    up = up / max(np.linalg.norm(up), 1e-12)
    radius = float(np.linalg.norm(centres - target, axis=1).mean())
    return {"target": target.tolist(), "up": up.tolist(), "radius": radius}


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world at position looking at target: z = (position - target)/|.|, x = up x z."""
    z_axis = position - target
    z_axis = z_axis / np.linalg.norm(z_axis)
    x_axis = np.cross(up, z_axis)
    x_axis = x_axis / np.linalg.norm(x_axis)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x_axis, np.cross(z_axis, x_axis), z_axis, position
    return c2w


def orbit_poses(orbit: dict[str, Any], num_frames: int, elevation_deg: float) -> np.ndarray:
    """num_frames cameras on a circle around orbit["target"], about orbit["up"], in the scene frame."""
    target, up = np.asarray(orbit["target"]), np.asarray(orbit["up"])
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = np.cross(up, helper)
    first /= np.linalg.norm(first)
    second = np.cross(up, first)
    elevation = math.radians(elevation_deg)
    poses = []
    for angle in np.linspace(0.0, 2 * math.pi, num_frames, endpoint=False):
        horizontal = math.cos(angle) * first + math.sin(angle) * second
        direction = math.cos(elevation) * horizontal + math.sin(elevation) * up
        poses.append(look_at(target + orbit["radius"] * direction, target, up))
    return np.stack(poses)


def render_orbit(
    run_dir: Path | str,
    num_frames: int,
    out_dir: Path | str,
    width: int | None = None,
    height: int | None = None,
    elevation_deg: float = DEFAULT_ORBIT_ELEVATION_DEG,
    video_format: str = "gif",
    checkpoint: str = "latest",
    progress: Any = None,
    device: str = "auto",
    path: VideoPath = "captured",
) -> Path:
    """Render a video: out_dir/orbit_000.png ... and out_dir/orbit.<gif|mp4>; its path. path "captured":
    through the registered cameras of a photo scene (an orbit for Blender and .npz data, whose cameras
    are spread over a sphere, and for runs that do not record them); "orbit": a circle round the scene at
    elevation_deg."""
    if num_frames < 1:
        raise ValueError(f"an orbit needs at least one frame, got {num_frames}")
    run = load_run(run_dir, checkpoint, device=device)
    width = width or run.camera.width
    height = height or run.camera.height
    camera = view_camera(run, width, height, None, None)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    if path == "captured" and run.photos and run.cameras is not None:
        poses = path_poses(run.cameras, run.capture(), num_frames)
    else:
        poses = orbit_poses(run.orbit, num_frames, elevation_deg)

    def frames() -> Iterator[np.ndarray]:  # rendered one at a time as the encoder asks for them
        for index, c2w_scene in enumerate(poses):
            pose = torch.as_tensor(c2w_scene, dtype=torch.float32, device=run.device)
            frame = to_uint8(
                render_image(run.model, pose, camera, run.scene, run.background, run.config.chunk_rays).rgb
            )
            Image.fromarray(frame).save(out_dir / f"orbit_{index:03d}.png")
            if progress is not None:
                progress("render", (index + 1) / num_frames)
            yield frame

    return write_video(frames(), out_dir / f"orbit.{video_format}")
