"""Sizes chosen for the time budget: the training photos' long side from the measured step time, and the
views (video frames and held-out renders) kept within a share of the training time.

Pure functions of measured rates; neural.training measures them (a short timed probe) and records the
choice in the run's config.json ("train_size").
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

#: The budget should draw every training pixel about this many times (steps x batch rays / pixels).
PIXEL_PASSES = 2.0
#: A chosen training size never goes below this long side (nor above the photos' own).
MIN_TRAIN_SIDE = 200
#: The probe loads the photos at this long side (its steps cost what full-size ones do: a step is a batch
#: of rays whatever the image size) and times PROBE_STEPS steps after PROBE_WARMUP_STEPS.
PROBE_MAX_SIDE = 200
PROBE_WARMUP_STEPS = 2
PROBE_STEPS = 6
#: Rays rendered (no gradients) to time rendering.
PROBE_RENDER_RAYS = 4096
#: The views stage (video and held-out renders) takes at most this share of the training time.
VIEWS_SHARE = 0.2
#: Smaller views are cut no further: below this long side, and this many frames, a video shows nothing.
MIN_VIEW_SIDE = 64
MIN_VIDEO_FRAMES = 8
#: Views over their share shrink to this long side before they lose frames: smaller, a frame is not
#: recognisable (a loaded CPU once cut a 36-frame video to 76x50 px).
WATCHABLE_VIEW_SIDE = 160


@dataclass(frozen=True)
class MeasuredRates:
    """What the probe measured on this machine for this model and data."""

    seconds_per_step: float
    render_seconds_per_ray: float


@dataclass(frozen=True)
class TrainSize:
    """The training size chosen for a budget, as recorded in config.json."""

    max_side: int
    full_side: int
    budget_steps: int
    seconds_per_step: float | None
    render_seconds_per_ray: float | None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ViewsPlan:
    """Video frames and sizes that fit the views' share of the training time, and their expected seconds."""

    frames: int
    video_max_side: int
    held_out_max_side: int
    seconds: float


def time_calls(call: Callable[[], object], warmup: int, repeats: int) -> float:
    """Mean wall-clock seconds of call() over `repeats` calls after `warmup` untimed ones."""
    for _ in range(warmup):
        call()
    start = time.perf_counter()
    for _ in range(repeats):
        call()
    return (time.perf_counter() - start) / max(repeats, 1)


def budget_steps(steps: int | None, minutes: float | None, seconds_per_step: float | None) -> int | None:
    """Steps the budget trains: `steps`, else minutes / (seconds per step); None when unknown."""
    if steps is not None:
        return steps
    if minutes is None or not seconds_per_step:
        return None
    return max(1, int(60.0 * minutes / seconds_per_step))


def train_max_side(steps: int, batch_rays: int, num_images: int, width: int, height: int) -> int:
    """The long side at which steps x batch_rays = PIXEL_PASSES x num_images x W' x H' (W', H' the photos
    scaled by one factor), within [MIN_TRAIN_SIDE, max(W, H)]."""
    full_side = max(width, height)
    pixels_per_image = steps * batch_rays / (PIXEL_PASSES * max(num_images, 1))
    scale = math.sqrt(pixels_per_image / (width * height))
    return int(min(full_side, max(MIN_TRAIN_SIDE, round(full_side * scale))))


def scaled_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """(W', H') with the long side at most max_side, aspect kept, both even and at least 8."""
    scale = min(1.0, max_side / max(width, height))
    return max(8, 2 * round(width * scale / 2)), max(8, 2 * round(height * scale / 2))


def views_seconds(
    render_seconds_per_ray: float, width: int, height: int, frames: int, video_side: int, held_out: int,
    held_out_side: int,
) -> float:  # fmt: skip
    """Expected seconds to render `frames` video frames and `held_out` views at their long sides."""
    video = math.prod(scaled_size(width, height, video_side))
    evaluation = math.prod(scaled_size(width, height, held_out_side))
    return render_seconds_per_ray * (frames * video + held_out * evaluation)


def plan_views(
    train_seconds: float, render_seconds_per_ray: float | None, width: int, height: int, frames: int,
    video_side: int, held_out: int, held_out_side: int, share: float = VIEWS_SHARE,
) -> ViewsPlan:  # fmt: skip
    """The asked-for views when they fit share x train_seconds; else smaller (both sides by one factor, to
    WATCHABLE_VIEW_SIDE), then fewer video frames (to MIN_VIDEO_FRAMES), then smaller again (to
    MIN_VIEW_SIDE); never more or larger than asked. Unknown rate or share 0: as asked."""
    if not render_seconds_per_ray or share <= 0:
        return ViewsPlan(frames, video_side, held_out_side, math.nan)

    def cost(frame_count: int, video: int, evaluation: int) -> float:
        rate = render_seconds_per_ray
        return views_seconds(rate, width, height, frame_count, video, held_out, evaluation)

    allowed = share * train_seconds

    def shrunk(frame_count: int, floor: int) -> tuple[int, int]:
        """Both asked sides by the factor that fits frame_count frames (cost grows with the pixels), each
        kept at least at floor or at its asked size if smaller."""
        shrink = math.sqrt(allowed / cost(frame_count, video_side, held_out_side))
        return tuple(min(side, max(floor, round(side * shrink))) for side in (video_side, held_out_side))

    asked = cost(frames, video_side, held_out_side)
    if asked <= allowed:
        return ViewsPlan(frames, video_side, held_out_side, asked)
    video, evaluation = shrunk(frames, WATCHABLE_VIEW_SIDE)
    per_frame = cost(1, video, evaluation) - cost(0, video, evaluation)
    fixed = cost(0, video, evaluation)
    if fixed + frames * per_frame > allowed:
        frames = min(frames, max(MIN_VIDEO_FRAMES, int((allowed - fixed) / per_frame)))
        if cost(frames, video, evaluation) > allowed:
            video, evaluation = shrunk(frames, MIN_VIEW_SIDE)
    return ViewsPlan(frames, video, evaluation, cost(frames, video, evaluation))


#: Reconstruction seconds per photo of about 6 megapixels on the 2-core CPU (Herz-Jesus-P8: 8 photos in
#: 16 s, fountain-P11: 11 in 27 s, README's SfM benchmark).
RECONSTRUCTION_SECONDS_PER_PHOTO = 2.5


def expected_seconds(minutes: float | None, photos: int, views_share: float) -> dict[str, float] | None:
    """Expected seconds of a scene's stages and their total, for a time budget (None for a step count:
    its time depends on the machine): reconstruction by photo count, training = minutes, views at most
    views_share of it."""
    if minutes is None:
        return None
    stages = {
        "reconstruction": RECONSTRUCTION_SECONDS_PER_PHOTO * photos,
        "training": 60.0 * minutes,
        "views": views_share * 60.0 * minutes,
    }
    return {**stages, "total": sum(stages.values())}
