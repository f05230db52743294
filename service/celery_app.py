"""Celery: the same job functions on as many worker machines as needed, with a Redis broker.

Start a worker with `celery -A service.celery_app worker --concurrency 1` and the same SFMNERF_* settings
as the API (database URL, data folder on a shared volume, broker URL, executor=celery), and a render
worker with `-Q renders` (renders never queue behind a long job). Long jobs:
acks_late and prefetch 1, so a worker takes one job at a time and a job is acknowledged when it ends; the
broker's visibility timeout lies above the longest allowed job (Redis would otherwise hand a still-running
job's message to another worker after 1 hour). A message delivered again (visibility timeout, or a worker
process that died: task_reject_on_worker_lost) never runs its job twice: the claim in the job store is
fenced, and the second delivery only records the end of an attempt whose worker process is gone.
Each task carries its kind's maximum runtime as Celery time limits. Workers report progress into the same
database as the API.
"""

from __future__ import annotations

import os
import socket
from typing import Any

from celery import Celery
from celery.exceptions import SoftTimeLimitExceeded, TimeLimitExceeded
from celery.signals import task_failure, worker_process_init

from service.renders import RENDER_TASK, run_render_task
from service.settings import ServiceSettings

RUN_JOB_TASK = "sfmnerf.run_job"
RENDER_QUEUE = "renders"
PROCESS_START_SECONDS = 300.0
"""How long a fresh worker process may take to start (Celery's default of 4 s killed processes that were
still importing PyTorch on a busy machine, then started and killed the next one, and no task ran)."""
VISIBILITY_MARGIN_SECONDS = 3600.0
"""The default visibility timeout: the longest maximum runtime of any job kind plus this margin."""


def visibility_timeout(settings: ServiceSettings) -> float:
    """Seconds Redis waits before it hands an unacknowledged message to another worker."""
    if settings.broker_visibility_timeout_seconds is not None:
        return settings.broker_visibility_timeout_seconds
    return settings.longest_job_seconds + VISIBILITY_MARGIN_SECONDS


def make_celery(settings: ServiceSettings) -> Celery:
    app = Celery("sfmnerf", broker=settings.broker_url)
    timeout = visibility_timeout(settings)
    app.conf.update(
        task_acks_late=True,
        worker_prefetch_multiplier=1,
        # A worker process that died puts its message back; the next delivery finds the attempt's
        # process gone and records the job failed (it does not run it again).
        task_reject_on_worker_lost=True,
        task_ignore_result=True,  # state and results live in the job store
        # Renders never wait behind a long job: their own queue, served by `worker -Q renders`.
        task_routes={RENDER_TASK: {"queue": RENDER_QUEUE}},
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
        worker_proc_alive_timeout=PROCESS_START_SECONDS,
        broker_transport_options={
            "visibility_timeout": timeout,
            # sweep for messages past their visibility timeout often enough for short timeouts too
            "unacked_restore_interval": max(0.5, min(10.0, timeout / 4)),
            "unacked_restore_throttle": 1,
        },
    )
    app.task(name=RUN_JOB_TASK, bind=True)(_run_job)
    app.task(name=RENDER_TASK, acks_late=False)(run_render_task)
    return app


def _worker_name(task: Any) -> str:
    """The worker as the API shows it (no PID: that stays in the job's `pid` column)."""
    return f"celery {task.request.hostname or socket.gethostname()}"


def _run_job(task: Any, job_id: str) -> str | None:
    """Claims the queued job and runs it; a delivery that cannot claim it runs nothing."""
    from service.runner import TimeLimit, execute

    settings = ServiceSettings()
    store = _store(settings)
    attempt = store.claim(job_id, worker=_worker_name(task), pid=os.getpid())
    if attempt is None:
        _another_delivery(store, settings, task, job_id)
        return None
    soft_limit = (task.request.timelimit or (None, None))[1]
    limit = TimeLimit(SoftTimeLimitExceeded, soft_limit) if soft_limit else None
    state = execute(store, job_id, attempt, settings, limit)  # the API's sender threads send its webhook
    return str(state) if state else None


def _another_delivery(store: Any, settings: ServiceSettings, task: Any, job_id: str) -> None:
    """This job's task arrived again while the job is running (visibility timeout, or its worker process
    died): it is never started a second time; a dead worker process on this node ends the job failed."""
    from service.db import JobState, process_exists
    from service.runner import complete_job

    job = store.get(job_id)
    if job is None or job.state != JobState.running or job.task_id != task.request.id:
        return
    if job.worker == _worker_name(task) and job.pid and not process_exists(job.pid):
        complete_job(
            store,
            settings,
            job_id,
            job.attempt,
            JobState.failed,
            error="the Celery worker process running it died (killed, or out of memory)",
        )
    else:
        store.append_log(
            job_id, [f"a second delivery of this job's task was ignored: attempt {job.attempt} is running"]
        )


_stores: dict[str, Any] = {}


def _store(settings: ServiceSettings) -> Any:
    """One job store (engine and connection pool) per worker process and database."""
    from service.db import JobStore

    url = settings.resolved_database_url
    if url not in _stores:
        _stores[url] = JobStore(url, migrate=False)
    return _stores[url]


@worker_process_init.connect
def _import_job_libraries(**_: Any) -> None:
    """Each worker process imports the heavy libraries before its first task, so a job's soft time limit
    can never stop an import halfway: a half-imported torch fails every later task of that process. (Not in
    the parent before it forks: importing OpenBLAS and OpenCV starts threads there.)"""
    import estimation.pipeline  # noqa: F401  (OpenCV, GTSAM)
    import neural.inference  # noqa: F401  (PyTorch; what renders use)
    import neural.training  # noqa: F401


@task_failure.connect
def _mark_failed(
    sender: Any = None,
    task_id: str | None = None,
    exception: BaseException | None = None,
    args: Any = None,
    **_: Any,
) -> None:
    """A task that failed outside `execute` (its hard time limit, an error before the job started)."""
    from service.db import JobState
    from service.runner import complete_job, runtime_exceeded

    if not args or getattr(sender, "name", None) != RUN_JOB_TASK:  # a render's failure is its own answer
        return
    settings = ServiceSettings()
    store = _store(settings)
    job = store.get(args[0])
    if job is not None and job.state == JobState.running and job.task_id == task_id:
        if isinstance(exception, TimeLimitExceeded):
            reason = runtime_exceeded(job.kind, settings.max_runtime_seconds(job.kind))
        else:
            reason = f"the Celery worker process failed: {type(exception).__name__}: {exception}"
        complete_job(store, settings, job.id, job.attempt, JobState.failed, error=reason)


app = make_celery(ServiceSettings())
