"""A video uploaded in place of photos (the `images` field holding one video file): stored under its
sanitized name, its size checked before anything is decoded, then its container probed in the validation
process (`check_input_video`: supported format, a decodable first frame, duration and frame size within the
service's limits). The reconstruction job finds it with `input_video` and reconstructs its keyframes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from estimation.io.images import VIDEO_SUFFIXES
from service.settings import ServiceSettings
from service.uploads import inside, invalid, sanitize_filename, save_stream, too_large

FIELD = "images"
VIDEO_MEDIA_TYPE_PREFIX = "video/"


class Upload(Protocol):
    """What the service reads of an uploaded file (fastapi.UploadFile has these)."""

    filename: str | None
    content_type: str | None
    file: Any


@dataclass(frozen=True)
class SavedVideo:
    """A video stored in the job folder: its final name and byte count."""

    name: str
    size: int


def is_video_upload(upload: Upload) -> bool:
    """A video by its name's suffix or its declared media type (video/*)."""
    suffix = Path(upload.filename or "").suffix.lower()
    return suffix in VIDEO_SUFFIXES or (upload.content_type or "").startswith(VIDEO_MEDIA_TYPE_PREFIX)


def save_video(uploads: Sequence[Upload], folder: Path, settings: ServiceSettings) -> SavedVideo:
    """Stores the one uploaded video into folder; 422 when it comes with other files or lacks a video
    suffix, 413 beyond SFMNERF_MAX_INPUT_VIDEO_BYTES (counted before anything is decoded)."""
    if len(uploads) != 1:
        raise invalid(f"{FIELD}: upload either photos or one video, not {len(uploads)} files with a video")
    upload = uploads[0]
    name = sanitize_filename(upload.filename, FIELD)
    if Path(name).suffix.lower() not in VIDEO_SUFFIXES:
        raise invalid(f"{FIELD}: {name} is sent as {upload.content_type}; a video must be named "
                      f"{'/'.join(VIDEO_SUFFIXES)}")
    target = inside(folder, name)
    size = save_stream(upload.file, target)
    if size > settings.max_input_video_bytes:
        raise too_large(f"{FIELD}: {name} has {size} bytes, more than the limit "
                        f"SFMNERF_MAX_INPUT_VIDEO_BYTES={settings.max_input_video_bytes}")
    return SavedVideo(name=name, size=size)


def check_input_video(arguments: dict[str, Any], settings: ServiceSettings) -> None:
    """In the validation process: the video's container, first frame, duration and frame size (422 naming
    the file when it is corrupt or unsupported, 413 beyond a limit)."""
    from estimation.errors import InputError
    from estimation.io.video import probe_video

    path, name = Path(arguments["path"]), arguments["name"]
    try:
        info = probe_video(path)
    except InputError as error:
        raise invalid(f"{FIELD}: {str(error).replace(str(path), name)}") from None
    if info.width * info.height > settings.max_input_video_pixels:
        raise too_large(f"{FIELD}: {name} has frames of {info.width}x{info.height} pixels, more than the "
                        f"limit SFMNERF_MAX_INPUT_VIDEO_PIXELS={settings.max_input_video_pixels}")
    if info.duration_s > settings.max_input_video_seconds:
        raise too_large(f"{FIELD}: {name} lasts {info.duration_s:.1f} s, more than the limit "
                        f"SFMNERF_MAX_INPUT_VIDEO_SECONDS={settings.max_input_video_seconds:g}")


def input_video(folder: Path) -> Path | None:
    """The uploaded video of a job's input folder, or None when it holds photos (or is missing: the
    reconstruction then names the missing folder)."""
    if not Path(folder).is_dir():
        return None
    videos = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    return videos[0] if videos else None
