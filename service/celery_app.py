"""The Celery worker: `celery -A service.celery_app worker` registers the job, render and reconstruction-chunk
tasks (`service.spread`) on the configuration of `service.celery_config` and runs them.

Start a worker with `celery -A service.celery_app worker --concurrency 1` and the same SFMNERF_* settings
as the API (database URL, data folder on a shared volume, broker URL, executor=celery), and a render
worker with `-Q renders` (renders never queue behind a long job). A message delivered again (visibility
timeout, or a worker process that died: task_reject_on_worker_lost) never runs its job twice: the claim in
the job store is fenced, and the second delivery only records the end of an attempt whose worker process is
gone. Each task carries its kind's maximum runtime as Celery time limits. Workers report progress into the
same database as the API.
"""

from __future__ import annotations

import os
import socket
from typing import Any

from celery import Celery
from celery.exceptions import SoftTimeLimitExceeded, TimeLimitExceeded
from celery.signals import task_failure, worker_process_init

from service.celery_config import RENDER_TASK, RUN_JOB_TASK, SPREAD_TASK, make_celery
from service.job_end import complete_job, runtime_exceeded
from service.kinds import JobState
from service.renders import run_render_task
from service.runner import TimeLimit, execute
from service.settings import ServiceSettings
from service.spread import run_spread_task
from service.store.job_store import JobStore
from service.store.leases import process_exists


def _worker_name(task: Any) -> str:
    """The worker as the API shows it (no PID: that stays in the job's `pid` column)."""
    return f"celery {task.request.hostname or socket.gethostname()}"


def _run_job(task: Any, job_id: str) -> str | None:
    """Claims the queued job and runs it; a delivery that cannot claim it runs nothing."""
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


_stores: dict[str, JobStore] = {}


def _store(settings: ServiceSettings) -> JobStore:
    """One job store (engine and connection pool) per worker process and database."""
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


def make_worker_app(settings: ServiceSettings) -> Celery:
    """The configured Celery app with the job and render tasks registered (what a worker runs)."""
    app = make_celery(settings)
    app.task(name=RUN_JOB_TASK, bind=True)(_run_job)
    app.task(name=RENDER_TASK, acks_late=False)(run_render_task)
    app.task(name=SPREAD_TASK)(run_spread_task)
    return app


app = make_worker_app(ServiceSettings())
