"""Short H.264 clips for the video tests and benchmarks, encoded with PyAV from lego's views."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from estimation.io.export import opengl_c2w_to_opencv_pose
from estimation.types import CameraPose

LEGO_TRAIN = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "lego_200" / "train"


def encode_clip(frames: list[np.ndarray], path: Path, fps: int = 10, metadata: dict[str, str] | None = None,
                crf: int = 18) -> Path:
    """(H, W, 3) uint8 RGB frames as an H.264 MP4 (yuv420p); `metadata` written as container tags."""
    import av

    height, width = frames[0].shape[:2]
    options = {"movflags": "use_metadata_tags"} if metadata else {}
    with av.open(str(path), mode="w", options=options) as container:
        for key, value in (metadata or {}).items():
            container.metadata[key] = value
        stream = container.add_stream("libx264", rate=Fraction(fps))
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": str(crf), "preset": "veryfast"}
        for rgb in frames:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            container.mux(stream.encode(frame))
        container.mux(stream.encode(None))
    return path


def lego_centres() -> dict[str, np.ndarray]:
    """Camera centre (world) of each lego train view by file name."""
    return {name: pose.center for name, pose in lego_true_poses().items()}


def lego_true_poses() -> dict[str, CameraPose]:
    """World-to-camera (OpenCV axes) true pose of each lego train view by file name."""
    frames = json.loads((LEGO_TRAIN.parent / "transforms_train.json").read_text())["frames"]
    return {Path(frame["file_path"]).name + ".png":
            opengl_c2w_to_opencv_pose(np.array(frame["transform_matrix"])) for frame in frames}


def walk_order(centres: dict[str, np.ndarray], count: int, max_step_deg: float = 45.0) -> list[str]:
    """Up to `count` view names along a nearest-neighbour walk over the camera centres, from the first name:
    the order a hand-held camera moving around the object would see them in. The walk stops before a step
    of more than `max_step_deg` around the object (the views a greedy walk leaves for last are far apart:
    no camera path jumps there)."""
    names = sorted(centres)
    walk = [names[0]]
    left = set(names[1:])
    while left and len(walk) < count:
        here = centres[walk[-1]]
        nearest = min(left, key=lambda name: (float(np.linalg.norm(centres[name] - here)), name))
        cosine = here @ centres[nearest] / (np.linalg.norm(here) * np.linalg.norm(centres[nearest]))
        if np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) > max_step_deg:
            break
        walk.append(nearest)
        left.remove(nearest)
    return walk


def lego_view(name: str) -> np.ndarray:
    """The view's RGB pixels composited on white (as benchmarks/bench_sfm.py's lego set)."""
    with Image.open(LEGO_TRAIN / name) as image:
        rgba = np.asarray(image.convert("RGBA"), float) / 255.0
    return np.rint(255 * (rgba[..., :3] * rgba[..., 3:] + 1.0 - rgba[..., 3:])).astype(np.uint8)


def held_views(names: list[str], hold: int, blur_first_of: tuple[int, ...] = (), blur_sigma: float = 2.5
               ) -> tuple[list[np.ndarray], list[str]]:
    """Each view repeated `hold` times (a camera pausing on each viewpoint), the first frame of the views
    numbered in `blur_first_of` Gaussian-blurred (a shaky start); also each frame's view name."""
    frames, sources = [], []
    for number, name in enumerate(names):
        rgb = lego_view(name)
        for repeat in range(hold):
            blurred = repeat == 0 and number in blur_first_of
            frames.append(cv2.GaussianBlur(rgb, (0, 0), blur_sigma) if blurred else rgb)
            sources.append(name)
    return frames, sources
