"""A video as input: its frames decoded (PyAV, FFmpeg's libraries in the wheel: no ffmpeg program), the
blurred ones dropped, keyframes chosen by how far the view moved since the last one, and those written as
ordinary JPEG images, so every later stage (features, mapper, NeRF) reads a folder of photos.

Two passes over the video keep the memory bounded: the first measures each frame's sharpness and its
optical flow from the previous frame on small grey frames, the second converts only the keyframes.
Frame index = position in presentation order, counted from 0; keyframes are named by it (000123.jpg), so
their names sort in video order (`estimation.features.pairs.sequence_order`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import ExifTags, Image

from estimation.config import VideoConfig
from estimation.errors import InputError
from estimation.io.images import FULL_FRAME_DIAGONAL_MM, MIN_IMAGES, VIDEO_SUFFIXES
from estimation.types import ProgressCallback

SUPPORTED_CONTAINERS = ("mov,mp4,m4a,3gp,3g2,mj2", "matroska,webm", "avi")
"""FFmpeg demuxer names accepted: MP4/QuickTime (phones), Matroska/WebM and AVI; any other format FFmpeg
happens to recognise in the bytes (image sequences, playlists, network protocols) is refused."""
FOCAL_35MM_KEY_SUFFIXES = ("focal_length.35mm_equivalent", "focallengthin35mmfilm", "focal_length_35mm")
"""Container or stream metadata keys (lower case) ending so carry the 35 mm equivalent focal length, e.g.
QuickTime's com.apple.quicktime.camera.focal_length.35mm_equivalent."""
FRAME_NAME = "{:06d}.jpg"
SECONDS_PER_MINUTE = 60.0
MM_RESOLUTION_UNIT = 4
"""EXIF FocalPlaneResolutionUnit for millimetres."""
FLOW_CORNER_QUALITY = 0.01
FLOW_CORNER_MIN_DISTANCE_PX = 7
FLOW_MAX_FORWARD_BACKWARD_PX = 1.0
"""A KLT track counts as surviving only when tracking it back lands within this of where it started."""
SPACING_SEARCH_STEPS = 40
"""Bisection steps of the keyframe spacing that meets the keyframes-per-minute bounds."""
LOG_FLOOR = 1e-6


@dataclass(frozen=True)
class VideoInfo:
    """What the container says about a video: format, codec, upright size (rotation applied), frame rate,
    duration and the 35 mm equivalent focal length when its metadata carries one."""

    name: str
    container: str
    codec: str
    width: int
    height: int
    fps: float
    duration_s: float
    rotation_deg: int                # counter-clockwise turn applied to the stored frames to show them
    focal_35mm: float | None


@dataclass(frozen=True)
class FrameMotion:
    """How the view moved from one frame to the next: median KLT flow as a fraction of the image diagonal,
    and the share of tracked corners that survived (1.0 when there was nothing to track)."""

    flow: float
    survival: float


@dataclass(frozen=True)
class VideoAnalysis:
    """Per decoded frame (index = frame number): sharpness (variance of the Laplacian) and the motion from
    the previous frame (frame 0: none)."""

    sharpness: np.ndarray            # (N,) float
    flow: np.ndarray                 # (N,) fraction of the diagonal
    survival: np.ndarray             # (N,) in [0, 1]


@dataclass(frozen=True)
class KeyframeSelection:
    """The chosen frame numbers (ascending) and the novelty spacing that chose them (1.0: the thresholds of
    VideoConfig as given; larger or smaller to meet the keyframes-per-minute bounds)."""

    indices: list[int]
    spacing: float


@dataclass(frozen=True)
class VideoKeyframes:
    """The keyframes of a video written into `folder` (one JPEG per keyframe), and how they were chosen."""

    folder: Path
    info: VideoInfo
    paths: list[Path]
    frames_decoded: int
    blurred_frames: int
    selection: KeyframeSelection
    seconds: float

    def summary(self) -> dict:
        """report.json's `video` entry."""
        info = self.info
        return {
            "file": info.name, "container": info.container, "codec": info.codec, "width": info.width,
            "height": info.height, "fps": round(info.fps, 3), "duration_s": round(info.duration_s, 3),
            "rotation_deg": info.rotation_deg, "frames_decoded": self.frames_decoded,
            "blurred_frames": self.blurred_frames, "keyframes": len(self.paths),
            "keyframe_spacing": round(self.selection.spacing, 4),
            "focal_35mm": info.focal_35mm,
            "focal_source": "container metadata" if info.focal_35mm is not None else "none",
            "frames_folder": self.folder.name, "seconds": round(self.seconds, 3),
        }


def is_video(path: Path) -> bool:
    """Whether `path` is a file with a video suffix (VIDEO_SUFFIXES)."""
    path = Path(path)
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def _focal_35mm(metadata: dict[str, str]) -> float | None:
    """The first positive finite 35 mm equivalent focal length among the metadata's focal keys."""
    for key, value in metadata.items():
        if key.lower().endswith(FOCAL_35MM_KEY_SUFFIXES):
            try:
                focal = float(value)
            except ValueError:
                continue
            if math.isfinite(focal) and focal > 0:
                return focal
    return None


def _open(path: Path):  # -> av.container.InputContainer (av is imported where videos are read)
    """The video's container and its first video stream; InputError naming the file otherwise."""
    import av

    try:
        container = av.open(str(path), mode="r")
    except (av.FFmpegError, OSError, ValueError) as error:
        raise InputError(f"{path}: not a readable video ({error})") from None
    if container.format.name not in SUPPORTED_CONTAINERS:
        container.close()
        raise InputError(f"{path}: a {container.format.name!r} file is not a supported video "
                         f"(MP4/MOV, MKV/WebM or AVI)")
    if not container.streams.video:
        container.close()
        raise InputError(f"{path}: the file holds no video stream")
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"
    return container, stream


def _first_frame_rotation(path: Path, container, stream) -> int:
    """The display rotation of the first frame (counter-clockwise degrees, 0/90/180/270), from its display
    matrix; InputError naming the file when no frame decodes."""
    import av

    try:
        frame = next(container.decode(stream), None)
    except (av.FFmpegError, ValueError) as error:
        raise InputError(f"{path}: the video is damaged ({error})") from None
    if frame is None:
        raise InputError(f"{path}: no frame of the video decodes")
    return int(round(frame.rotation / 90.0)) * 90 % 360


def probe_video(path: Path) -> VideoInfo:
    """The container's description of the video (its first frame decoded); InputError naming the file
    when it is not a readable video of a supported container."""
    path = Path(path)
    container, stream = _open(path)
    with container:
        codec = stream.codec_context
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        fps = float(rate) if rate else 0.0
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        else:
            duration = (container.duration or 0) / 1_000_000
        rotation = _first_frame_rotation(path, container, stream)
        width, height = (codec.height, codec.width) if rotation % 180 else (codec.width, codec.height)
        metadata = {**container.metadata, **stream.metadata}
        if fps <= 0 or width <= 0 or height <= 0:
            raise InputError(f"{path}: the video stream has no frame rate or size")
        return VideoInfo(name=path.name, container=container.format.name, codec=codec.name, width=width,
                         height=height, fps=fps, duration_s=duration, rotation_deg=rotation,
                         focal_35mm=_focal_35mm(metadata))


def decoded_frames(path: Path) -> Iterator:
    """The video's frames (av.VideoFrame) in presentation order; InputError naming the file when the
    stream breaks off with an error."""
    import av

    container, stream = _open(Path(path))
    with container:
        try:
            yield from container.decode(stream)
        except (av.FFmpegError, ValueError) as error:
            raise InputError(f"{path}: the video is damaged ({error})") from None


def sharpness(gray: np.ndarray) -> float:
    """Var(Laplacian(I)): the energy of the second derivatives, which blur removes first."""
    return float(cv2.Laplacian(gray, cv2.CV_32F).var())


def blurred_frames(sharpness_values: np.ndarray, window: int, ratio: float) -> np.ndarray:
    """s_t < ratio * median(s_{t-window..t+window}): frames much less sharp than their neighbours (the
    scene's own texture changes slowly, motion blur and focus hunting from one frame to the next)."""
    values = np.asarray(sharpness_values, float)
    # Mirrored at the ends without repeating the end frame itself (a blurred first frame would otherwise
    # fill its own window).
    padded = np.pad(values, window, mode="reflect" if len(values) > window else "edge")
    neighbourhood = np.lib.stride_tricks.sliding_window_view(padded, 2 * window + 1)
    return values < ratio * np.median(neighbourhood, axis=1)


def frame_motion(previous: np.ndarray, current: np.ndarray, max_corners: int) -> FrameMotion:
    """Median |x_t - x_{t-1}| / diagonal of the corners of `previous` tracked (pyramidal KLT, checked
    forward-backward) into `current`, and the share of them that survived."""
    corners = cv2.goodFeaturesToTrack(previous, max_corners, FLOW_CORNER_QUALITY, FLOW_CORNER_MIN_DISTANCE_PX)
    if corners is None:
        return FrameMotion(0.0, 1.0)
    forward, status, _ = cv2.calcOpticalFlowPyrLK(previous, current, corners, None)
    backward, status_back, _ = cv2.calcOpticalFlowPyrLK(current, previous, forward, None)
    round_trip = np.linalg.norm((backward - corners).reshape(-1, 2), axis=1)
    tracked = (status.ravel() == 1) & (status_back.ravel() == 1) & (round_trip < FLOW_MAX_FORWARD_BACKWARD_PX)
    if not tracked.any():
        return FrameMotion(0.0, 0.0)
    diagonal = float(np.hypot(*previous.shape[:2]))
    flow = np.linalg.norm((forward - corners).reshape(-1, 2)[tracked], axis=1)
    return FrameMotion(float(np.median(flow)) / diagonal, float(tracked.mean()))


def frame_novelty(flow: np.ndarray, survival: np.ndarray, config: VideoConfig) -> np.ndarray:
    """n_t = max(flow_t / keyframe_motion, log(survival_t) / log(min_overlap)): each frame's step towards
    the next keyframe, 1 being a keyframe's worth of flow or of lost overlap (survival multiplies along the
    frames, so its logarithm adds up as flow does)."""
    lost = np.log(np.maximum(np.asarray(survival, float), LOG_FLOOR)) / math.log(config.min_overlap)
    return np.maximum(np.asarray(flow, float) / config.keyframe_motion, lost)


def greedy_keyframes(novelty: np.ndarray, usable: np.ndarray, spacing: float, bridge_share: float = 0.0
                     ) -> list[int]:
    """The first usable frame, then each usable frame at which the novelty summed since the last keyframe
    reaches `spacing` (novelty keeps adding up over unusable frames). A keyframe reached by a jump (the
    novelty from the last usable frame before it alone reaches `spacing`) is preceded by that frame when
    it lies bridge_share x spacing or more from the last keyframe (0: never): the keyframes on either side
    of the jump would share little, the frame before it shares more with each (a bridge)."""
    keyframes: list[int] = []
    accumulated = 0.0
    before, before_accumulated = None, 0.0     # the last usable frame since the last keyframe
    for index, (step, ok) in enumerate(zip(novelty, usable, strict=True)):
        accumulated += step
        if ok and (not keyframes or accumulated >= spacing):
            bridges = (bridge_share > 0 and before is not None
                       and before_accumulated >= bridge_share * spacing
                       and accumulated - before_accumulated >= spacing)
            keyframes.extend([before, index] if bridges else [index])
            accumulated, before = 0.0, None
        elif ok:
            before, before_accumulated = index, accumulated
    return keyframes


def keyframe_bounds(duration_s: float, config: VideoConfig) -> tuple[int, int]:
    """(fewest, most) keyframes of a video this long (keyframes per minute of VideoConfig)."""
    minutes = duration_s / SECONDS_PER_MINUTE
    fewest = max(MIN_IMAGES, math.ceil(config.min_keyframes_per_minute * minutes))
    return fewest, max(fewest, math.floor(config.max_keyframes_per_minute * minutes))


def select_keyframes(novelty: np.ndarray, blurred: np.ndarray, duration_s: float, config: VideoConfig
                     ) -> KeyframeSelection:
    """`greedy_keyframes` over the sharp frames at spacing 1, or at the spacing (bisected) that brings the
    count within `keyframe_bounds`: larger when there are too many, smaller (never below
    min_spacing_factor) when too few."""
    usable = ~np.asarray(blurred, bool)
    fewest, most = keyframe_bounds(duration_s, config)

    def count(spacing: float) -> int:
        return len(greedy_keyframes(novelty, usable, spacing, config.bridge_share))

    spacing = 1.0
    if count(spacing) > most:
        low, high = spacing, max(float(np.sum(novelty)), spacing) + 1.0   # high: one keyframe
        for _ in range(SPACING_SEARCH_STEPS):
            middle = 0.5 * (low + high)
            low, high = (middle, high) if count(middle) > most else (low, middle)
        spacing = high
    elif count(spacing) < fewest:
        low, high = config.min_spacing_factor, spacing
        if count(low) < fewest:
            spacing = low
        else:
            for _ in range(SPACING_SEARCH_STEPS):
                middle = 0.5 * (low + high)
                low, high = (middle, high) if count(middle) >= fewest else (low, middle)
            spacing = low
    return KeyframeSelection(greedy_keyframes(novelty, usable, spacing, config.bridge_share), spacing)


def _analysis_size(info: VideoInfo, max_side: int) -> tuple[int, int]:
    """(width, height) of the stored frames scaled so the longer side is at most max_side (even sizes)."""
    stored_w, stored_h = (info.height, info.width) if info.rotation_deg % 180 else (info.width, info.height)
    scale = min(1.0, max_side / max(stored_w, stored_h))
    return max(2, round(stored_w * scale / 2) * 2), max(2, round(stored_h * scale / 2) * 2)


def analyse_video(path: Path, info: VideoInfo, config: VideoConfig,
                  progress: ProgressCallback | None = None) -> VideoAnalysis:
    """Sharpness and motion of every frame, on grey frames downscaled to analysis_max_side."""
    width, height = _analysis_size(info, config.analysis_max_side)
    expected = max(1, round(info.duration_s * info.fps))
    values: list[float] = []
    motions: list[FrameMotion] = [FrameMotion(0.0, 1.0)]
    previous = None
    for frame in decoded_frames(path):
        if len(values) == config.max_frames:
            raise InputError(f"{path}: more than {config.max_frames} frames (VideoConfig.max_frames)")
        gray = frame.reformat(width=width, height=height, format="gray").to_ndarray()
        values.append(sharpness(gray))
        if previous is not None:
            motions.append(frame_motion(previous, gray, config.tracked_corners))
        previous = gray
        if progress is not None and len(values) % 30 == 0:
            progress("decoding video", min(len(values) / expected, 1.0))
    return VideoAnalysis(sharpness=np.array(values), flow=np.array([m.flow for m in motions[:len(values)]]),
                         survival=np.array([m.survival for m in motions[:len(values)]]))


def frame_exif(focal_35mm: float, width: int, height: int) -> Image.Exif:
    """EXIF giving f_px = f35 / 43.27 mm * diagonal_px to `exif_focal`: FocalLength f35 mm on the 35 mm
    equivalent frame of the image's aspect (diagonal 43.27 mm), i.e. FocalPlaneXResolution =
    diagonal_px / 43.27 pixels per mm (the fraction kept exact, which FocalLengthIn35mmFilm's whole
    millimetres would not)."""
    exif = Image.Exif()
    exif[ExifTags.IFD.Exif] = {
        ExifTags.Base.FocalLength: float(focal_35mm),
        ExifTags.Base.FocalPlaneXResolution: float(np.hypot(width, height)) / FULL_FRAME_DIAGONAL_MM,
        ExifTags.Base.FocalPlaneResolutionUnit: MM_RESOLUTION_UNIT,
    }
    return exif


def write_keyframes(path: Path, info: VideoInfo, indices: list[int], folder: Path, config: VideoConfig,
                    progress: ProgressCallback | None = None) -> list[Path]:
    """The frames numbered `indices`, upright, downscaled to max_side, written as folder/FRAME_NAME JPEGs
    (with the container's focal length as EXIF when it has one)."""
    folder.mkdir(parents=True, exist_ok=True)
    wanted = set(indices)
    scale = min(1.0, config.max_side / max(info.width, info.height))
    width, height = round(info.width * scale), round(info.height * scale)
    exif = frame_exif(info.focal_35mm, width, height) if info.focal_35mm is not None else None
    written: list[Path] = []
    for index, frame in enumerate(decoded_frames(path)):
        if index not in wanted:
            continue
        rgb = np.rot90(frame.to_ndarray(format="rgb24"), info.rotation_deg // 90)
        image = Image.fromarray(np.ascontiguousarray(rgb))
        if scale < 1.0:
            image = image.resize((width, height), Image.Resampling.LANCZOS)
        target = folder / FRAME_NAME.format(index)
        image.save(target, quality=config.jpeg_quality, **({"exif": exif} if exif is not None else {}))
        written.append(target)
        if progress is not None:
            progress("writing keyframes", len(written) / len(wanted))
        if len(written) == len(wanted):
            break
    return written


def extract_keyframes(path: Path, folder: Path, config: VideoConfig = VideoConfig(),
                      progress: ProgressCallback | None = None) -> VideoKeyframes:
    """The video's sharp keyframes (`select_keyframes`) written into `folder` as JPEGs; InputError naming the
    file when it is not a readable video or gives fewer than two keyframes."""
    path, folder = Path(path), Path(folder)
    started = time.perf_counter()
    info = probe_video(path)
    report = progress or (lambda stage, fraction: None)
    analysis = analyse_video(path, info, config, lambda stage, fraction: report(stage, 0.7 * fraction))
    if len(analysis.sharpness) < MIN_IMAGES:
        raise InputError(f"{path}: {len(analysis.sharpness)} frame(s) decoded, need at least {MIN_IMAGES}")
    blurred = blurred_frames(analysis.sharpness, config.blur_window, config.blur_ratio)
    duration = len(analysis.sharpness) / info.fps
    selection = select_keyframes(frame_novelty(analysis.flow, analysis.survival, config), blurred, duration,
                                 config)
    if len(selection.indices) < MIN_IMAGES:
        raise InputError(f"{path}: the camera hardly moves: {len(selection.indices)} keyframe(s) from "
                         f"{len(analysis.sharpness)} frames, need at least {MIN_IMAGES}")
    paths = write_keyframes(path, info, selection.indices, folder, config,
                            lambda stage, fraction: report(stage, 0.7 + 0.3 * fraction))
    return VideoKeyframes(folder=folder, info=info, paths=paths, frames_decoded=len(analysis.sharpness),
                          blurred_frames=int(blurred.sum()), selection=selection,
                          seconds=time.perf_counter() - started)
