"""The scene supervisor: where a scene advances. A thread of the API process moves every running scene
(photos -> poses -> radiance field -> views, service.pipeline) on when the child jobs of its stage end.

A reconstruction that registered enough images leads to a NeRF job on its poses, a trained NeRF to an orbit
video job and a held-out evaluation job, each created through the actions (a client's NeRF and video jobs
go through the same ones, with all their checks). A child that fails or is cancelled fails the scene at
that stage with the child's reason. A stage refused as busy (every upload check taken, the owner's queue
full: a 429 with Retry-After) waits and is tried again after that delay, as a client would.
Each scene is its own unit of failure: any error in one scene's step fails that scene with the reason
(its finished stages stay available, and a retry re-runs only the failed stage) and never stops the loop
for the others.
"""

from __future__ import annotations

import json
import logging
import time

from service.actions.nerf import NerfInputs, TrainOptions, create_nerf, queue_evaluation, queue_video
from service.actions.scenes import owner_client, scene_lock, scene_owner, stage_jobs
from service.errors import ServiceError, retry_after_seconds
from service.executor import Executor
from service.kinds import JobState
from service.layout import RECONSTRUCTION_REPORT, output_dir
from service.loop_thread import LoopThread
from service.params import EvaluationParams, VideoParams
from service.pipeline import DONE, HELD_OUT_SPLIT, SceneOptions, registration_problem, views_plan
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job, Scene, SceneChild, utcnow
from service.uploads import without_server_paths

log = logging.getLogger(__name__)
SUPERVISOR_POLL_SECONDS = 0.5
MAX_SCENES_PER_PASS = 1000
STAGE_NAMES = {"reconstruction": "reconstruction", "nerf": "NeRF", "views": "orbit video and held-out views"}


class SceneSteps:
    """One step of a running scene: start its stage's jobs if missing, or act on their outcome."""

    def __init__(self, store: JobStore, executor: Executor, settings: ServiceSettings) -> None:
        self.store, self.executor, self.settings = store, executor, settings
        self._busy_until: dict[str, float] = {}   # scene id -> monotonic time its busy stage is tried again

    def advance(self, scene: Scene) -> None:
        """Moves the scene on; a busy refusal makes it wait (`_wait`), any other refusal or error in its step
        fails this scene with the reason."""
        if time.monotonic() < self._busy_until.get(scene.id, 0.0):
            return
        try:
            self._advance(scene)
            self._busy_until.pop(scene.id, None)
        except ServiceError as refused:
            retry_after = retry_after_seconds(refused)
            if retry_after is not None:
                self._wait(scene, refused.detail, retry_after)
            else:
                self._fail(scene, f"the {STAGE_NAMES[scene.stage]} could not start: {refused.detail}")
        except Exception as error:  # one scene's failure must not stall the others
            log.exception("scene %s failed at stage %s", scene.id, scene.stage)
            reason = without_server_paths(f"{type(error).__name__}: {error}", self.settings)
            self._fail(scene, f"unexpected error: {reason}")

    def _advance(self, scene: Scene) -> None:
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
        report_path = output_dir(self.settings, job.id) / RECONSTRUCTION_REPORT
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
        config = SceneOptions.model_validate(scene.params).train_config
        inputs = NerfInputs(
            train=TrainOptions(model=config["model"], options=json.dumps(config)),
            reconstruction_id=scene.reconstruction_job_id,
        )
        client = owner_client(scene_owner(self.store, scene))
        child = SceneChild(scene.id, "nerf_job_id")
        job = create_nerf(self.store, self.executor, self.settings, client, inputs, scene_child=child)
        self.store.update_scene(scene.id, log=f"NeRF job {job.id} started")

    def _start_views(self, scene: Scene) -> None:
        options = SceneOptions.model_validate(scene.params)
        nerf = self.store.get(scene.nerf_job_id)
        train_seconds = float((nerf.result or {}).get("seconds") or 0.0) if nerf else 0.0
        run_dir = output_dir(self.settings, scene.nerf_job_id)
        plan, (width, height) = views_plan(options, run_dir, train_seconds)
        if scene.video_job_id is None:
            video = VideoParams(num_frames=plan.frames, width=width, height=height)
            child = SceneChild(scene.id, "video_job_id")
            queue_video(self.store, self.executor, self.settings, scene.nerf_job_id, video, scene_child=child)
        if scene.evaluation_job_id is None:
            held_out = EvaluationParams(split=HELD_OUT_SPLIT, max_side=plan.held_out_max_side)
            child = SceneChild(scene.id, "evaluation_job_id")
            queue_evaluation(self.store, self.executor, scene.nerf_job_id, held_out, scene_child=child)
        self.store.update_scene(scene.id, log="orbit video and held-out renders queued")

    def _wait(self, scene: Scene, reason: str, seconds: float) -> None:
        """The scene stays running at its stage, tried again in `seconds`; its log says why, once per wait."""
        if scene.id not in self._busy_until:
            self.store.update_scene(scene.id, log=f"the {STAGE_NAMES[scene.stage]} waits: {reason}")
        self._busy_until[scene.id] = time.monotonic() + seconds

    def _fail(self, scene: Scene, reason: str) -> None:
        self._busy_until.pop(scene.id, None)
        self.store.update_scene(
            scene.id,
            state=JobState.failed,
            error=f"{scene.stage}: {reason}",
            finished_at=utcnow(),
            log=f"failed at stage {scene.stage}: {reason}",
        )


class SceneSupervisor:
    """The thread that advances running scenes, started and stopped with the app."""

    def __init__(self, steps: SceneSteps) -> None:
        self.steps = steps
        self._advancing = LoopThread("sfmnerf-scenes", self._loop)

    def start(self) -> None:
        self._advancing.start()

    def stop(self) -> None:
        self._advancing.stop()

    def advance_all(self) -> None:
        """One pass over the running scenes, each advanced on its own (SceneSteps.advance fails only it)."""
        store = self.steps.store
        scenes, _ = store.list_scenes(state=JobState.running, limit=MAX_SCENES_PER_PASS)
        for scene in scenes:
            with scene_lock:
                current = store.get_scene(scene.id)
                if current is not None and current.state == JobState.running:
                    self.steps.advance(current)

    def _loop(self) -> None:
        while not self._advancing.stopping.wait(SUPERVISOR_POLL_SECONDS):
            try:
                self.advance_all()
            except Exception:  # a database hiccup must not end supervision
                log.exception("scene supervisor pass failed")
