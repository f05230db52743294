"""How a job ends: the one place a job's end is recorded, whoever sees it end.

The job itself (`runner.execute`), its supervisor or reaper (`executor`), a Celery signal and a client's
cancel all end jobs here: the fenced state change, the closing log line and the webhook marked due in the
store's outbox (the API's `webhooks.WebhookSender` threads deliver it, also after a restart).
"""

from __future__ import annotations

from service.kinds import JobState
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job
from service.uploads import without_server_paths


def announce_end(store: JobStore, job_id: str, line: str) -> None:
    """The closing log line of a job that just ended, and its webhook marked due in the outbox (any process
    may: the API's sender threads deliver it, also after a restart)."""
    store.append_log(job_id, [line])
    store.queue_webhook(job_id)


def complete_job(
    store: JobStore,
    settings: ServiceSettings,
    job_id: str,
    attempt: int,
    state: JobState,
    *,
    error: str | None = None,
    result: dict | None = None,
) -> bool:
    """Ends a running attempt (fenced by `attempt`) and announces it (`announce_end`);
    False if it no longer owns the job. The error names no server path (whoever records it)."""
    error = without_server_paths(error, settings) if error else error
    if not store.finish(job_id, attempt, state, error=error, result=result):
        return False
    shown = f" ({error})" if error and state != JobState.succeeded else ""
    announce_end(store, job_id, f"finished: {state}{shown}")
    return True


def request_cancel(store: JobStore, job_id: str, *, announce: bool = True) -> Job | None:
    """A queued job ends cancelled at once (announced, unless it is about to be deleted); a running one is
    flagged, and its executor stops it and records the end (`complete_job`)."""
    job = store.request_cancel(job_id)
    if announce and job is not None and job.state == JobState.cancelled:
        announce_end(store, job_id, "finished: cancelled before it started")
    return job


def runtime_exceeded(kind: str, seconds: float) -> str:
    """The error of a job stopped at its kind's maximum runtime (`seconds`)."""
    minutes = seconds / 60.0
    return (
        f"the {kind} job ran longer than its maximum runtime of {minutes:g} minutes "
        f"(SFMNERF_MAX_RUNTIME_{kind.upper()}_MINUTES) and was stopped"
    )
