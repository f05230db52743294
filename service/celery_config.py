"""Celery's configuration, shared by whoever sends tasks (the API's executor and render queue) and the
workers (`service.celery_app` registers the tasks on it). Tasks are sent by name, so a sender never imports
the task code.

Long jobs: acks_late and prefetch 1, so a worker takes one job at a time and a job is acknowledged when it
ends; the broker's visibility timeout lies above the longest allowed job (Redis would otherwise hand a
still-running job's message to another worker after 1 hour). Renders have their own queue.
"""

from __future__ import annotations

from celery import Celery

from service.settings import ServiceSettings

RUN_JOB_TASK = "sfmnerf.run_job"
RENDER_TASK = "sfmnerf.render"
SPREAD_TASK = "sfmnerf.reconstruction_chunk"
"""One chunk of a reconstruction's feature extraction or matching (`service.spread`)."""
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
    return app
