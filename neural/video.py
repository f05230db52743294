"""Frames -> an animated GIF (always available) or an MP4 (needs the imageio-ffmpeg package)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

VIDEO_FORMATS = ("gif", "mp4")


def write_video(frames: Sequence[np.ndarray], path: Path, fps: float = 20.0) -> Path:
    """Write (H,W,3) uint8 frames to path; the suffix (.gif or .mp4) picks the format."""
    import imageio.v2 as imageio

    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in VIDEO_FORMATS:
        raise ValueError(f"{path}: video format must be one of {', '.join(VIDEO_FORMATS)}")
    if suffix == "gif":
        imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
        return path
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ValueError(f"{path}: writing MP4 needs the imageio-ffmpeg package; use .gif instead") from None
    imageio.mimsave(path, list(frames), fps=fps, macro_block_size=1)
    return path
