"""Actions on jobs of every kind: look one up for a client, cancel, retry and delete it."""

from __future__ import annotations

import os
import shutil
import time

from service.auth import ANONYMOUS, Client
from service.errors import conflict, not_found
from service.executor import Executor
from service.housekeeping import delete_job_and_files
from service.job_end import request_cancel
from service.kinds import TERMINAL_STATES, JobKind, JobState
from service.layout import input_dir
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job, new_job_id

DELETE_WAIT_SECONDS = 10.0
RUNNING_POLL_SECONDS = 0.1


def find_job(store: JobStore, job_id: str, kind: JobKind | None = None, client: Client = ANONYMOUS) -> Job:
    """The job, or 404 naming the id (also when it is of another kind or not the client's)."""
    job = store.get(job_id)
    if job is None or (kind is not None and job.kind != kind) or not client.may_see(job.owner):
        what = f"{kind} job" if kind else "job"
        raise not_found(f"{what} {job_id} not found")
    return job


def cancel_job(store: JobStore, executor: Executor, settings: ServiceSettings, job_id: str) -> Job:
    """Cancels a queued or running job (409 when it already ended); the job as it is once its process
    stopped (it usually does within a second) or after the grace period."""
    job = find_job(store, job_id)
    if job.state in TERMINAL_STATES:
        raise conflict(f"job {job_id} is already {job.state}")
    job = request_cancel(store, job_id) or job
    executor.cancel(job_id)
    return wait_while_running(store, job_id, settings.cancel_grace_seconds + 1.0) or job


def retry_job(store: JobStore, executor: Executor, settings: ServiceSettings, job_id: str) -> Job:
    """A new job with the same kind, inputs, source, webhook and owner as a failed or cancelled one."""
    job = find_job(store, job_id)
    if job.state not in (JobState.failed, JobState.cancelled):
        raise conflict(f"only failed or cancelled jobs can be retried; job {job_id} is {job.state}")
    if job.source_job_id and store.get(job.source_job_id) is None:
        raise conflict(f"the job's source {job.source_job_id} was deleted")
    new_id = new_job_id()
    source_inputs = input_dir(settings, job_id)
    if source_inputs.is_dir():
        shutil.copytree(source_inputs, input_dir(settings, new_id), copy_function=_link_or_copy)
    retry = store.create(
        JobKind(job.kind),
        job.params,
        job_id=new_id,
        source_job_id=job.source_job_id,
        retry_of=job_id,
        webhook_url=job.webhook_url,
        owner=job.owner,
    )
    store.append_log(new_id, [f"retry of job {job_id}"])
    executor.submit(new_id)
    return retry


def delete_job(store: JobStore, executor: Executor, settings: ServiceSettings, job_id: str) -> None:
    """Deletes a job and its files; a job still queued or running is cancelled first."""
    job = find_job(store, job_id)
    if job.state not in TERMINAL_STATES:
        request_cancel(store, job_id, announce=False)  # it is deleted: nobody is told it ended
        executor.cancel(job_id)
        wait_while_running(store, job_id, DELETE_WAIT_SECONDS)
    delete_job_and_files(store, settings, job_id)


def wait_while_running(store: JobStore, job_id: str, seconds: float) -> Job | None:
    """The job once it is no longer running, or as it is after `seconds`."""
    deadline = time.monotonic() + seconds
    while (job := store.get(job_id)) is not None and job.state == JobState.running:
        if time.monotonic() > deadline:
            break
        time.sleep(RUNNING_POLL_SECONDS)
    return job


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
