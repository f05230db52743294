"""The job functions and the code that runs one job attempt, shared by local job processes and Celery.

`execute(store, job_id, attempt, settings)` runs the job whose attempt the caller claimed: it reports
progress and log lines into the job store, heartbeats, stops when cancelled, and records the end through
`service.job_end`. The heavy libraries (`estimation`, `neural`) are imported inside the job functions, so
that the processes that only supervise or serve (the API, a Celery parent) never load them.
"""

from __future__ import annotations

import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from service.job_end import complete_job, runtime_exceeded
from service.kinds import JobKind, JobState, require_every_kind
from service.layout import input_dir, job_dir, output_dir
from service.params import EvaluationParams, NerfParams, ReconstructionParams, VideoParams, parse_params
from service.pipeline import render_held_out
from service.settings import ServiceSettings
from service.spread import CeleryStages
from service.store.job_store import JobStore
from service.store.tables import Job
from service.uploads import without_server_paths
from service.video_uploads import input_video

PROGRESS_WRITE_INTERVAL_SECONDS = 0.5
"""Progress of one stage is written at most this often (a NeRF step loop calls back every step)."""
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
log = logging.getLogger(__name__)


@dataclass
class JobContext:
    """What a job function gets: its job, folders, and callbacks into the job store."""

    store: JobStore
    job: Job
    attempt: int
    settings: ServiceSettings
    stop_reason: str | None = None
    _last_stage: str | None = None
    _last_write: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def params(self) -> Any:
        """The job's typed parameters (service.params: one model per job kind)."""
        return parse_params(self.job.kind, self.job.params)

    @property
    def input_dir(self) -> Path:
        return input_dir(self.settings, self.job.id)

    @property
    def output_dir(self) -> Path:
        return output_dir(self.settings, self.job.id)

    def log(self, line: str) -> None:
        self.store.append_log(self.job.id, [without_server_paths(line, self.settings)])

    def progress(self, stage: str, fraction: float) -> None:
        """ProgressCallback: stage name and overall fraction; writes are throttled, stage changes logged."""
        now = time.monotonic()
        with self._lock:
            stage_changed = stage != self._last_stage
            if not stage_changed and now - self._last_write < PROGRESS_WRITE_INTERVAL_SECONDS:
                return
            self._last_stage, self._last_write = stage, now
        if stage_changed:
            self.log(f"stage: {stage} ({fraction:.0%})")
        if not self.store.report_progress(self.job.id, self.attempt, stage, fraction):
            self.stop_reason = self.stop_reason or "the job was cancelled or taken over"

    def should_stop(self) -> bool:
        return self.stop_reason is not None


class _WithoutTraceback(logging.Formatter):
    """The record's message only: tracebacks stay in the server's log, never in a job's."""

    def formatException(self, ei: Any) -> str:  # noqa: N802 (logging's name)
        return ""

    def formatStack(self, stack_info: str) -> str:  # noqa: N802 (logging's name)
        return ""


class _StoreLogHandler(logging.Handler):
    """Copies the job's Python log records (estimation, neural) into its log lines."""

    def __init__(self, context: JobContext) -> None:
        super().__init__(logging.INFO)
        self.context = context
        self.setFormatter(_WithoutTraceback(LOG_FORMAT))

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.context.log(self.format(record).rstrip("\n"))
        except Exception:  # logging must never break the job
            self.handleError(record)


def _heartbeat_loop(context: JobContext, stop: threading.Event) -> None:
    while not stop.wait(context.settings.heartbeat_seconds):
        owned, cancel = context.store.heartbeat(context.job.id, context.attempt)
        if cancel:
            context.stop_reason = "cancelled"
        elif not owned:
            context.stop_reason = "the job was cancelled or taken over"


# ---- the job functions --------------------------------------------------------------------------------


def spread_stages(context: JobContext) -> CeleryStages | None:
    """The Celery tasks that extract and match the features of a reconstruction of at least
    `spread_min_images` images, with the Celery executor (`service.spread`); None: this worker does all."""
    from estimation.io.images import list_images

    settings = context.settings
    if settings.executor != "celery" or len(list_images(context.input_dir)) < settings.spread_min_images:
        return None
    return CeleryStages(settings, context.job.id, context.attempt, context.log)


def run_reconstruction(context: JobContext) -> dict[str, Any]:
    """estimation.reconstruct on the uploaded folder; the report stays in output/report.json."""
    from estimation import ReconstructionConfig, reconstruct

    params: ReconstructionParams = context.params
    config = ReconstructionConfig.model_validate(params.config)
    if config.sift.workers == 0:  # "all cores": this job's share of them, beside the other jobs
        config.sift.workers = context.settings.threads_per_job()
    shutil.rmtree(context.output_dir, ignore_errors=True)  # a re-run starts from scratch
    images = input_video(context.input_dir) or context.input_dir
    stages = spread_stages(context)
    try:
        result = reconstruct(images, context.output_dir, config, progress=context.progress, stages=stages)
    finally:
        if stages is not None:
            stages.close()
    model = result.model
    return {
        "registered_images": len(model.poses),
        "unregistered_images": len(model.unregistered),
        "points": int(len(model.points)),
    }


def nerf_dataset_path(settings: ServiceSettings, job: Job) -> Path:
    """Where a NeRF job's training data lives: its upload, or its source reconstruction's output."""
    params: NerfParams = parse_params(job.kind, job.params)
    if job.source_job_id or params.dataset is None:
        return output_dir(settings, job.source_job_id)
    return job_dir(settings, job.id) / params.dataset


def run_nerf(context: JobContext) -> dict[str, Any]:
    """neural.train into output/ (the run folder); resumes from the latest checkpoint after a restart."""
    from neural import TrainConfig, list_checkpoints, train

    run_dir = context.output_dir
    resume = bool(context.job.resume and run_dir.is_dir() and list_checkpoints(run_dir))
    if resume:
        context.log(f"resuming from the checkpoint at step {max(c.step for c in list_checkpoints(run_dir))}")
        config = None
    else:
        shutil.rmtree(run_dir, ignore_errors=True)
        config = TrainConfig.model_validate(context.params.train_config)

    def on_metrics(metrics: dict) -> None:
        context.log(
            "metrics: "
            + " ".join(f"{k}={v:.5g}" if isinstance(v, float) else f"{k}={v}" for k, v in metrics.items())
        )

    result = train(
        nerf_dataset_path(context.settings, context.job),
        run_dir,
        config,
        resume=resume,
        progress=context.progress,
        metrics_callback=on_metrics,
        should_stop=context.should_stop,
    )
    return _summary(result)


def run_video(context: JobContext) -> dict[str, Any]:
    """neural.render_orbit (along params.path) of the source NeRF job's latest checkpoint into output/."""
    from neural import render_orbit

    params: VideoParams = context.params
    shutil.rmtree(context.output_dir, ignore_errors=True)
    context.progress("rendering orbit", 0.0)
    path = render_orbit(
        output_dir(context.settings, context.job.source_job_id),
        params.num_frames,
        context.output_dir,
        params.width,
        params.height,
        progress=context.progress,
        path=params.path,
    )
    return {
        "file": str(Path(path).resolve().relative_to(job_dir(context.settings, context.job.id).resolve()))
    }


def run_evaluation(context: JobContext) -> dict[str, Any]:
    """The scene pipeline's held-out renders of the source NeRF job's latest checkpoint on its data
    (params: split, max_side): output/<image>.png per view and output/metrics.json."""
    from neural import TrainConfig
    from neural.artefacts import IMAGE_CACHE_DIR
    from neural.data import load_dataset_for
    from neural.inference import read_run_config

    params: EvaluationParams = context.params
    nerf_job = context.store.get(context.job.source_job_id)
    if nerf_job is None:
        raise ValueError(f"the NeRF job {context.job.source_job_id} was deleted")
    shutil.rmtree(context.output_dir, ignore_errors=True)
    context.progress("rendering held-out views", 0.0)
    run_dir = output_dir(context.settings, nerf_job.id)
    config = TrainConfig.model_validate(read_run_config(run_dir)["train"])  # as the run trained on its data
    data = nerf_dataset_path(context.settings, nerf_job)
    dataset = load_dataset_for(data, config, run_dir / IMAGE_CACHE_DIR)
    result = render_held_out(run_dir, dataset, params.max_side, params.split, context.output_dir)
    return {"views": len(result.per_image), "mean_psnr": result.mean_psnr, "mean_ssim": result.mean_ssim}


def _summary(result: Any) -> dict[str, Any]:
    """The scalar fields of a result dataclass (server paths left out: the API serves the files)."""
    fields = {name: getattr(result, name) for name in getattr(result, "__dataclass_fields__", {})}
    return {
        k: finite_or_none(v) for k, v in fields.items() if isinstance(v, (int, float, str, bool)) or v is None
    }


def finite_or_none(value: Any) -> Any:
    """NaN and infinities become None: JSON has no place for them."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


JOB_FUNCTIONS: dict[JobKind, Callable[[JobContext], dict[str, Any]]] = {
    JobKind.reconstruction: run_reconstruction,
    JobKind.nerf: run_nerf,
    JobKind.video: run_video,
    JobKind.evaluation: run_evaluation,
}
require_every_kind(JOB_FUNCTIONS, "job functions")


def _expected_error_types() -> tuple[type[Exception], ...]:
    """Errors that mean bad input or options: their message is the job's error, without a type name."""
    from estimation.errors import InputError
    from neural.errors import CheckpointError, DatasetError

    return InputError, DatasetError, CheckpointError


class TimeLimit(NamedTuple):
    """An executor's runtime limit that interrupts a job by raising `error_type` inside it (Celery's
    soft time limit): the job then fails with the maximum-runtime reason."""

    error_type: type[BaseException]
    seconds: float


def execute(
    store: JobStore,
    job_id: str,
    attempt: int,
    settings: ServiceSettings,
    time_limit: TimeLimit | None = None,
) -> JobState | None:
    """Runs one claimed attempt of a job to its end and records the outcome; returns the final state."""
    job = store.get(job_id)
    if job is None or job.attempt != attempt or job.state != JobState.running:
        return None
    context = JobContext(store=store, job=job, attempt=attempt, settings=settings)
    handler = _StoreLogHandler(context)
    root = logging.getLogger()
    root.addHandler(handler)
    previous_level = root.level
    root.setLevel(min(previous_level, logging.INFO) if previous_level else logging.INFO)
    stop_heartbeat = threading.Event()
    heartbeat = threading.Thread(target=_heartbeat_loop, args=(context, stop_heartbeat), daemon=True)
    heartbeat.start()
    context.log(f"attempt {attempt} of {job.kind} job started by {job.worker or 'a worker'}")
    state, error, result = JobState.failed, None, None
    unexpected: Exception | None = None
    started = time.monotonic()
    try:
        result = JOB_FUNCTIONS[job.kind](context)
        state = JobState.cancelled if context.should_stop() else JobState.succeeded
    except _expected_error_types() as exc:
        error = str(exc)
    except Exception as exc:  # any other failure ends the job with its reason, never a stuck job
        error = f"{type(exc).__name__}: {exc}"
        # The limit's exception can surface as another one (e.g. ImportError when it interrupts an import).
        if time_limit is not None and (
            isinstance(exc, time_limit.error_type) or time.monotonic() - started >= time_limit.seconds
        ):
            error = runtime_exceeded(job.kind, time_limit.seconds)
        else:
            unexpected = exc
    finally:
        stop_heartbeat.set()
        root.removeHandler(handler)
        root.setLevel(previous_level)
    if unexpected is not None:  # the traceback goes to the server's log, never to the job's
        log.error("%s job %s failed", job.kind, job_id, exc_info=unexpected)
    if state == JobState.cancelled:
        error = "cancelled"
    if complete_job(
        store,
        settings,
        job_id,
        attempt,
        state,
        error=error if state != JobState.succeeded else None,
        result=result,
    ):
        return state
    return None
