"""The scene pipeline: photos -> poses -> radiance field -> novel views, one definition for every caller.

`sfmnerf scene` runs it in one process (`run_scene`); the service runs each step as a child job of a scene
(`service.scene_supervisor` moves a scene from step to step, `service.runner` holds the job functions) with
the same options, checks and artefact names, all defined here: `SceneOptions`, `registration_problem`,
`views_plan`, `render_held_out`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from neural.budget import VIEWS_SHARE, ViewsPlan, plan_views
from neural.budget import scaled_size as orbit_size
from service.layout import RUN_CONFIG

STAGES = ("reconstruction", "nerf", "views")
DONE = "done"
STAGE_WEIGHTS = {"reconstruction": 0.2, "nerf": 0.65, "views": 0.15}
"""Each stage's share of a scene's overall progress (the NeRF training takes most of the time)."""
RECONSTRUCTION_DIR, NERF_DIR, ORBIT_DIR, HELD_OUT_DIR = "reconstruction", "nerf", "orbit", "held_out"
"""The folders `sfmnerf scene` writes, one per step."""
EVALUATION_FILE = "metrics.json"
"""PSNR and SSIM of the held-out views, per view and mean (beside their renders)."""
HELD_OUT_SPLIT = "val"

ProgressCallback = Callable[[str, float], None]


class SceneOptions(BaseModel):
    """What a scene does after its reconstruction (the reconstruction's options are its own)."""

    train_config: dict[str, Any] = Field(..., description="The NeRF's TrainConfig, validated.")
    min_registered_images: int = Field(
        3, ge=2, le=10_000, description="Fewest registered images to train on."
    )
    orbit_frames: int = Field(
        36, ge=1, le=720, description="Most frames of the video (fewer when the views would take longer "
        "than views_share of the training time).",
    )  # fmt: skip
    orbit_max_side: int = Field(200, ge=8, le=4096, description="Largest long side of the video, pixels.")
    held_out_max_side: int = Field(
        200, ge=8, le=4096, description="Held-out views are rendered downscaled to at most this side."
    )
    views_share: float = Field(
        VIEWS_SHARE, ge=0, le=100,
        description="The views (video and held-out renders) take at most this share of the training time: "
        "fewer frames or smaller renders when they would take longer (0: as asked).",
    )  # fmt: skip
    expected_seconds: dict[str, float] | None = Field(
        None,
        description="Expected seconds per stage and in total on a CPU, estimated when the scene started.",
    )


class StageFailed(Exception):
    """A step of the pipeline ended without what the next step needs (e.g. too few registered images)."""

    def __init__(self, stage: str, reason: str) -> None:
        super().__init__(f"{stage}: {reason}")
        self.stage, self.reason = stage, reason


def registration_problem(report: dict[str, Any], minimum: int) -> str | None:
    """Why a reconstruction (its report) is too small to train a NeRF on, or None."""
    registered, total = report.get("images_registered", 0), report.get("images_total", 0)
    if registered >= minimum:
        return None
    reasons = "; ".join(f"{u['image']}: {u['reason']}" for u in report.get("unregistered", []))
    return (
        f"the reconstruction registered {registered} of {total} images; a NeRF needs at least {minimum}"
        + (f" (not registered: {reasons})" if reasons else "")
    )


def views_plan(
    options: SceneOptions, run_dir: Path, train_seconds: float
) -> tuple[ViewsPlan, tuple[int, int]]:
    """The video frames and render sizes of a trained NeRF run's views stage: those asked for, cut to take
    at most views_share of the training time at the render rate recorded in its config.json
    (neural.budget); and the video's (width, height)."""
    run_config = json.loads((run_dir / RUN_CONFIG).read_text())
    camera, rates = run_config["camera"], run_config.get("train_size") or {}
    held_out = len(run_config.get("cameras", {}).get("held_out", []))
    plan = plan_views(
        train_seconds, rates.get("render_seconds_per_ray"), camera["width"], camera["height"],
        options.orbit_frames, options.orbit_max_side, held_out, options.held_out_max_side,
        options.views_share,
    )  # fmt: skip
    return plan, orbit_size(camera["width"], camera["height"], plan.video_max_side)


def downscaled(dataset: Any, max_side: int) -> Any:
    """A neural.Dataset with its images and intrinsics reduced by the smallest whole factor that brings the
    long side to at most max_side (pixel blocks averaged), for held-out renders at a cheap size."""
    import dataclasses

    import numpy as np

    from neural.training import downscale

    factor = max(1, math.ceil(max(dataset.width, dataset.height) / max_side))
    return dataclasses.replace(
        dataset,
        images=np.stack([downscale(image, factor) for image in dataset.images]),
        fx=dataset.fx / factor, fy=dataset.fy / factor, cx=dataset.cx / factor, cy=dataset.cy / factor,
    )  # fmt: skip


def render_held_out(run_dir: Path, dataset: Any, max_side: int, split: str, out_dir: Path) -> Any:
    """The run's renders of the dataset's held-out split at most max_side long, scored against the photos:
    out_dir/<image>.png per view and out_dir/metrics.json; returns neural's EvaluationResult."""
    from neural import evaluate

    result = evaluate(run_dir, downscaled(dataset, max_side), split, out_dir=out_dir)
    (out_dir / EVALUATION_FILE).write_text(json.dumps(result.to_dict(), indent=2))
    return result


@dataclass
class SceneOutcome:
    """What `run_scene` made: the reconstruction's report, the training and views results."""

    report: dict[str, Any]
    trained: Any
    video: Path
    held_out: Any
    seconds: dict[str, float] = field(default_factory=dict)


StageProgress = Callable[[str], AbstractContextManager[ProgressCallback]]
"""Opens a step by name; the callback it yields takes (what, fraction of the step)."""


def run_scene(
    photos_dir: Path, out_dir: Path, reconstruction_config: Any, options: SceneOptions, stage: StageProgress
) -> SceneOutcome:
    """Every step in this process: OUT/reconstruction, OUT/nerf, OUT/orbit and OUT/held_out. StageFailed
    when the reconstruction registered too few images (its output stays)."""
    from estimation import reconstruct
    from neural import TrainConfig, load_dataset, render_orbit, train

    seconds: dict[str, float] = {}

    @contextmanager
    def timed(name: str) -> Iterator[ProgressCallback]:
        started = time.perf_counter()
        with stage(name) as progress:
            yield progress
        seconds[name] = time.perf_counter() - started

    with timed("reconstruction") as progress:
        result = reconstruct(
            photos_dir, out_dir / RECONSTRUCTION_DIR, reconstruction_config, progress=progress
        )
    if problem := registration_problem(result.report, options.min_registered_images):
        raise StageFailed("reconstruction", f"{problem}; it is in {out_dir / RECONSTRUCTION_DIR}")
    config = TrainConfig.model_validate(options.train_config)
    with timed("nerf") as progress:
        trained = train(out_dir / RECONSTRUCTION_DIR, out_dir / NERF_DIR, config, progress=progress)
    with timed("views") as progress:
        plan, (width, height) = views_plan(options, out_dir / NERF_DIR, trained.seconds)
        video = render_orbit(
            out_dir / NERF_DIR, plan.frames, out_dir / ORBIT_DIR, width, height,
            progress=lambda _text, fraction: progress("orbit", fraction / 2),
        )  # fmt: skip
        held_out = render_held_out(
            out_dir / NERF_DIR, load_dataset(out_dir / RECONSTRUCTION_DIR), plan.held_out_max_side,
            HELD_OUT_SPLIT, out_dir / HELD_OUT_DIR,
        )  # fmt: skip
        progress("held-out views", 1.0)
    return SceneOutcome(result.report, trained, Path(video), held_out, seconds)
