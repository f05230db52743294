"""Frames -> an animated GIF (always available) or an MP4 (needs the imageio-ffmpeg package).

Frames are appended to the encoder one by one as they arrive, so a long video never sits in memory.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

VIDEO_FORMATS = ("gif", "mp4")


def write_video(frames: Iterable[np.ndarray], path: Path, fps: float = 20.0) -> Path:
    """Write (H,W,3) uint8 frames (any iterable, e.g. a generator rendering them) to path, streaming each
    frame to the encoder; the suffix (.gif or .mp4) picks the format."""
    import imageio.v2 as imageio

    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in VIDEO_FORMATS:
        raise ValueError(f"{path}: video format must be one of {', '.join(VIDEO_FORMATS)}")
    if suffix == "gif":
        options: dict = {"mode": "I", "duration": 1000.0 / fps, "loop": 0}
    else:
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ValueError(
                f"{path}: writing MP4 needs the imageio-ffmpeg package; use .gif instead"
            ) from None
        options = {"mode": "I", "fps": fps, "macro_block_size": 1}
    with imageio.get_writer(path, **options) as writer:
        for frame in frames:
            writer.append_data(frame)
    return path
