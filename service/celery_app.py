"""Celery: the same job functions on as many worker machines as needed, with a Redis broker.

Start a worker with `celery -A service.celery_app worker --concurrency 1` and the same SFMNERF_* settings
as the API (database URL, data folder on a shared volume, broker URL, executor=celery). Long jobs:
acks_late and prefetch 1, so a worker takes one job at a time and a job is acknowledged when it ends.
Workers report progress into the same database as the API.
"""

from __future__ import annotations

import os
import socket
from typing import Any

from celery import Celery
from celery.signals import task_failure

from service.settings import ServiceSettings

RUN_JOB_TASK = "sfmnerf.run_job"


def make_celery(settings: ServiceSettings) -> Celery:
    app = Celery("sfmnerf", broker=settings.broker_url)
    app.conf.update(
        task_acks_late=True,
        worker_prefetch_multiplier=1,
        task_reject_on_worker_lost=False,  # a worker process that died ends its job failed, not re-run
        task_ignore_result=True,  # state and results live in the job store
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
    )
    app.task(name=RUN_JOB_TASK, bind=True)(_run_job)
    return app


def _run_job(task: Any, job_id: str) -> str | None:
    """Claims the queued job and runs it; does nothing if it was cancelled or taken meanwhile."""
    from service.jobs import execute

    settings = ServiceSettings()
    store = _store(settings)
    worker = f"celery {task.request.hostname or socket.gethostname()}"
    attempt = store.claim(job_id, worker=worker, pid=os.getpid())
    if attempt is None:
        return None
    state = execute(store, job_id, attempt, settings)
    if state:  # sent from this process's sender threads: the task (and its worker slot) ends now
        from service import webhooks

        webhooks.enqueue_delivery(store, job_id, settings)
    return str(state) if state else None


_stores: dict[str, Any] = {}


def _store(settings: ServiceSettings) -> Any:
    """One job store (engine and connection pool) per worker process and database."""
    from service.db import JobStore

    url = settings.resolved_database_url
    if url not in _stores:
        _stores[url] = JobStore(url)
    return _stores[url]


@task_failure.connect
def _mark_failed(
    sender: Any = None,
    task_id: str | None = None,
    exception: BaseException | None = None,
    args: Any = None,
    **_: Any,
) -> None:
    """A task that failed outside `execute` (e.g. its worker process was killed): the job ends failed."""
    from service.db import JobState

    if not args:
        return
    store = _store(ServiceSettings())
    job = store.get(args[0])
    if job is not None and job.state == JobState.running and job.task_id == task_id:
        reason = f"the Celery worker process died: {type(exception).__name__}: {exception}"
        if store.finish(job.id, job.attempt, JobState.failed, error=reason):
            from service import webhooks

            webhooks.notify(store, job.id, ServiceSettings(), background=False)


app = make_celery(ServiceSettings())
