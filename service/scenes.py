"""Scenes: photos -> poses -> radiance field -> novel views, as a chain of ordinary child jobs.

POST /v1/scenes creates the reconstruction job (through the reconstruction route, with all its checks) and
the scene. `SceneSupervisor`, a thread of the API process, moves every running scene on when the child
job of its stage ends: a reconstruction that registered enough images leads to a NeRF job on its poses
(through the NeRF route's function), a trained NeRF to an orbit video job and a held-out evaluation job.
A child that fails or is cancelled fails the scene at that stage with the child's reason; every artifact
made so far stays, and a retry re-runs only the failed stage's jobs. The same flow runs in one process in
`sfmnerf scene` (service/commands/scene.py), sharing the checks below.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from typing import Any

from fastapi import HTTPException, Response
from pydantic import BaseModel, Field

from neural.budget import VIEWS_SHARE, ViewsPlan, plan_views
from neural.budget import scaled_size as orbit_size
from service.auth import ANONYMOUS, Client
from service.db import TERMINAL_STATES, Job, JobKind, JobState, JobStore, Scene, utcnow
from service.executor import Executor
from service.models import VideoRequest
from service.params import EvaluationParams
from service.runner import output_dir
from service.settings import ServiceSettings

log = logging.getLogger(__name__)

STAGES = ("reconstruction", "nerf", "views")
DONE = "done"
STAGE_WEIGHTS = {"reconstruction": 0.2, "nerf": 0.65, "views": 0.15}
"""Each stage's share of a scene's overall progress (the NeRF training takes most of the time)."""
SUPERVISOR_POLL_SECONDS = 0.5
scene_lock = threading.Lock()
"""Serialises the supervisor's steps with the routes' cancel, retry and delete of scenes."""


class SceneOptions(BaseModel):
    """What a scene does after its reconstruction (the reconstruction's options are its job's params)."""

    train_config: dict[str, Any] = Field(..., description="The NeRF's TrainConfig, validated.")
    min_registered_images: int = Field(
        3, ge=2, le=10_000, description="Fewest registered images to train on."
    )
    orbit_frames: int = Field(36, ge=1, le=720, description="Frames of the orbit video.")
    orbit_max_side: int = Field(200, ge=8, le=4096, description="Long side of the orbit video, pixels.")
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


def scene_owner(store: JobStore, scene: Scene) -> str | None:
    """The client a scene belongs to: the owner of its reconstruction job (the client that created it)."""
    job = store.get(scene.reconstruction_job_id) if scene.reconstruction_job_id else None
    return job.owner if job is not None else None


def owner_client(owner: str | None) -> Client:
    """Who a scene's child jobs are created as: its owner without admin rights (the anonymous admin of a
    service without tokens when it has none)."""
    return ANONYMOUS if owner is None else Client(name=owner, admin=False)


def registration_problem(report: dict[str, Any], minimum: int) -> str | None:
    """Why a reconstruction (its report.json) is too small to train a NeRF on, or None."""
    registered, total = report.get("images_registered", 0), report.get("images_total", 0)
    if registered >= minimum:
        return None
    reasons = "; ".join(f"{u['image']}: {u['reason']}" for u in report.get("unregistered", []))
    return (
        f"the reconstruction registered {registered} of {total} images; a NeRF needs at least {minimum}"
        + (f" (not registered: {reasons})" if reasons else "")
    )


def views_plan(
    options: SceneOptions, run_config: dict[str, Any], train_seconds: float
) -> tuple[ViewsPlan, tuple[int, int]]:
    """The video frames and render sizes of the views stage: those asked for, cut to take at most
    views_share of the training time at the render rate the training probe measured (neural.budget);
    and the video's (width, height)."""
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


def stage_jobs(scene: Scene, stage: str) -> list[str]:
    """The ids of the child jobs of one stage (those created so far)."""
    ids = {
        "reconstruction": [scene.reconstruction_job_id],
        "nerf": [scene.nerf_job_id],
        "views": [scene.video_job_id, scene.evaluation_job_id],
    }[stage]
    return [job_id for job_id in ids if job_id]


class SceneRunner:
    """Creates, advances, cancels, retries and deletes scenes through the job routes' own functions."""

    def __init__(self, store: JobStore, executor: Executor, settings: ServiceSettings) -> None:
        self.store, self.executor, self.settings = store, executor, settings

    # ---- moving on --------------------------------------------------------------------------------------

    def advance(self, scene: Scene) -> None:
        """One step of a running scene: start its stage's jobs if missing, or act on their outcome."""
        jobs = [self.store.get(job_id) for job_id in stage_jobs(scene, scene.stage)]
        if any(job is None for job in jobs):
            self._fail(scene, f"a {scene.stage} job of the scene was deleted")
            return
        ended = [job for job in jobs if job.state in (JobState.failed, JobState.cancelled)]
        if ended:
            job = ended[0]
            self._fail(scene, f"{job.kind} job {job.id} {job.state}: {job.error or job.state}")
            return
        if scene.stage == "reconstruction" and jobs[0].state == JobState.succeeded:
            self._after_reconstruction(scene, jobs[0])
        elif scene.stage == "nerf" and not jobs:
            self._start_nerf(scene)
        elif scene.stage == "nerf" and jobs[0].state == JobState.succeeded:
            self.store.update_scene(
                scene.id, stage="views", log="NeRF trained; rendering the orbit and held-out views"
            )
        elif scene.stage == "views" and len(jobs) < 2:
            self._start_views(scene)
        elif scene.stage == "views" and all(job.state == JobState.succeeded for job in jobs):
            self.store.update_scene(
                scene.id, state=JobState.succeeded, stage=DONE, finished_at=utcnow(), log="scene succeeded"
            )

    def _after_reconstruction(self, scene: Scene, job: Job) -> None:
        options = SceneOptions.model_validate(scene.params)
        report_path = output_dir(self.settings, job.id) / "report.json"
        report = json.loads(report_path.read_text()) if report_path.is_file() else {}
        problem = registration_problem(report, options.min_registered_images)
        if problem:
            self._fail(scene, problem)
            return
        self.store.update_scene(
            scene.id,
            stage="nerf",
            log=f"reconstruction registered {report['images_registered']} of {report['images_total']} images",
        )

    def _start_nerf(self, scene: Scene) -> None:
        from service.routes.nerf import create_nerf

        config = SceneOptions.model_validate(scene.params).train_config
        try:
            job = create_nerf(
                Response(), self.store, owner_client(scene_owner(self.store, scene)), self.executor,
                self.settings, dataset=None,
                reconstruction_id=scene.reconstruction_job_id, model=config["model"], steps=None,
                minutes=None, batch_rays=None, device=None, options=json.dumps(config), webhook_url=None,
            )  # fmt: skip
        except HTTPException as error:
            self._fail(scene, f"the NeRF could not start: {error.detail}")
            return
        self.store.update_scene(scene.id, nerf_job_id=job.id, log=f"NeRF job {job.id} started")

    def _start_views(self, scene: Scene) -> None:
        from service.routes.nerf import queue_video

        options = SceneOptions.model_validate(scene.params)
        values: dict[str, Any] = {}
        nerf = self.store.get(scene.nerf_job_id)
        train_seconds = float((nerf.result or {}).get("seconds") or 0.0) if nerf else 0.0
        run_config = json.loads((output_dir(self.settings, scene.nerf_job_id) / "config.json").read_text())
        plan, (width, height) = views_plan(options, run_config, train_seconds)
        if scene.video_job_id is None:
            request = VideoRequest(num_frames=plan.frames, width=width, height=height)
            try:
                values["video_job_id"] = queue_video(
                    scene.nerf_job_id, request, Response(), self.store, self.executor, self.settings
                ).id
            except HTTPException as error:
                self._fail(scene, f"the orbit video could not start: {error.detail}")
                return
        if scene.evaluation_job_id is None:
            job = self.store.create(
                JobKind.evaluation,
                EvaluationParams(split="val", max_side=plan.held_out_max_side),
                source_job_id=scene.nerf_job_id,
                owner=scene_owner(self.store, scene),
            )
            self.executor.submit(job.id)
            values["evaluation_job_id"] = job.id
        self.store.update_scene(scene.id, log="orbit video and held-out renders queued", **values)

    def _fail(self, scene: Scene, reason: str) -> None:
        self.store.update_scene(
            scene.id,
            state=JobState.failed,
            error=f"{scene.stage}: {reason}",
            finished_at=utcnow(),
            log=f"failed at stage {scene.stage}: {reason}",
        )

    # ---- actions on the whole scene ---------------------------------------------------------------------

    def cancel(self, scene: Scene) -> None:
        """Marks the scene cancelled and cancels its running child jobs (their processes are killed)."""
        from service.routes.jobs import cancel_job

        self.store.update_scene(scene.id, state=JobState.cancelled, finished_at=utcnow(), log="cancelled")
        for job_id in stage_jobs(scene, scene.stage):
            job = self.store.get(job_id)
            if job is not None and job.state not in TERMINAL_STATES:
                cancel_job(job_id, self.store, self.executor, self.settings)

    def retry(self, scene: Scene) -> None:
        """Runs the failed or cancelled jobs of the scene's stage again (new jobs); earlier stages stay.

        Raises ValueError when the stage's jobs all succeeded (a reconstruction that registered too few
        images would register as few again)."""
        from service.routes.jobs import retry_job

        again = {}
        for job_id in stage_jobs(scene, scene.stage):
            job = self.store.get(job_id)
            if job is not None and job.state in (JobState.failed, JobState.cancelled):
                again[job_id] = retry_job(job_id, Response(), self.store, self.executor, self.settings).id
        if scene.stage == "reconstruction" and not again:
            raise ValueError(f"{scene.error}; a retry would give the same: start a scene with more photos")
        field = {"reconstruction": ["reconstruction_job_id"], "nerf": ["nerf_job_id"]}.get(
            scene.stage, ["video_job_id", "evaluation_job_id"]
        )
        values = {name: again.get(getattr(scene, name), getattr(scene, name)) for name in field}
        self.store.update_scene(
            scene.id, state=JobState.running, error=None, finished_at=None,
            log=f"retry of stage {scene.stage}" + (f": jobs {', '.join(again.values())}" if again else ""),
            **values,
        )  # fmt: skip

    def delete(self, scene: Scene) -> None:
        """Cancels a running scene, then deletes its child jobs and the jobs they retried (files included)
        and the scene."""
        from service.routes.jobs import delete_job

        if scene.state not in TERMINAL_STATES:
            self.cancel(scene)
        for job_id in self.store.scene_job_ids(scene):
            delete_job(job_id, self.store, self.executor, self.settings)
        self.store.delete_scene(scene.id)


class SceneSupervisor:
    """The thread that advances running scenes, started and stopped with the app."""

    def __init__(self, runner: SceneRunner) -> None:
        self.runner = runner
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="sfmnerf-scenes", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread:
            self._thread.join(timeout=10)

    def _loop(self) -> None:
        while not self._stopping.wait(SUPERVISOR_POLL_SECONDS):
            try:
                scenes, _ = self.runner.store.list_scenes(state=JobState.running, limit=1000)
                for scene in scenes:
                    with scene_lock:
                        current = self.runner.store.get_scene(scene.id)
                        if current is not None and current.state == JobState.running:
                            self.runner.advance(current)
            except Exception:  # a database hiccup must not end supervision
                log.exception("scene supervisor iteration failed")
