"""/v1/jobs: list, inspect, follow logs, cancel, retry and delete jobs of every kind."""

from __future__ import annotations

import shutil
import time
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Response, status

from service.db import TERMINAL_STATES, Job, JobKind, JobState, JobStore
from service.deps import ClientDep, ExecutorDep, JobIdPath, SettingsDep, StoreDep, find_job
from service.housekeeping import delete_job as delete_job_and_files
from service.housekeeping import disk_space_problem
from service.models import ErrorOut, JobList, JobOut, LogsOut
from service.quotas import check_client_quota
from service.runner import announce_end, input_dir

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
NOT_FOUND = {404: {"model": ErrorOut, "description": "No job with this id."}}
MAX_PAGE = 500
MAX_LOG_LINES = 5000
DELETE_WAIT_SECONDS = 10.0
NO_SPACE = {507: {"model": ErrorOut, "description": "The server's disk is too full for new work."}}


def require_disk_space(settings: SettingsDep, store: StoreDep, client: ClientDep) -> None:
    """507 Insufficient Storage for new work while the disk is below SFMNERF_MIN_FREE_DISK_BYTES; the
    client's quotas (service.quotas): 429 or 507."""
    if (problem := disk_space_problem(settings)) is not None:
        raise HTTPException(status.HTTP_507_INSUFFICIENT_STORAGE, problem)
    check_client_quota(store, client, settings)


def accepted(response: Response, job: JobOut) -> JobOut:
    """202 Accepted with the job resource and its Location."""
    response.status_code = status.HTTP_202_ACCEPTED
    response.headers["Location"] = job.links["self"]
    return job


@router.get("", response_model=JobList, summary="List jobs, newest first")
def list_jobs(
    store: StoreDep,
    client: ClientDep,
    kind: Annotated[JobKind | None, Query(description="Only jobs of this kind.")] = None,
    state: Annotated[JobState | None, Query(description="Only jobs in this state.")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> JobList:
    owner = None if client.admin else client.name
    rows, total = store.list(kind=kind, state=state, owner=owner, limit=limit, offset=offset)
    return JobList(items=[JobOut.from_job(job) for job in rows], total=total, limit=limit, offset=offset)


@router.get("/{job_id}", response_model=JobOut, responses=NOT_FOUND, summary="One job's state and progress")
def get_job(job_id: JobIdPath, store: StoreDep) -> JobOut:
    return JobOut.from_job(find_job(store, job_id))


@router.get(
    "/{job_id}/logs", response_model=LogsOut, responses=NOT_FOUND, summary="Log lines from `offset` on"
)
def get_logs(
    job_id: JobIdPath,
    store: StoreDep,
    offset: Annotated[int, Query(ge=0, le=2**31, description="Lines already read.")] = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_LOG_LINES)] = 1000,
) -> LogsOut:
    find_job(store, job_id)
    lines = list(store.read_logs(job_id, offset, limit))
    return LogsOut(job_id=job_id, offset=offset, next_offset=offset + len(lines), lines=lines)


@router.post(
    "/{job_id}/cancel",
    response_model=JobOut,
    responses={**NOT_FOUND, 409: {"model": ErrorOut}},
    summary="Cancel a queued or running job (its process is killed)",
)
def cancel_job(job_id: JobIdPath, store: StoreDep, executor: ExecutorDep, settings: SettingsDep) -> JobOut:
    job = find_job(store, job_id)
    if job.state in TERMINAL_STATES:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id} is already {job.state}")
    job = store.request_cancel(job_id)
    executor.cancel(job_id)
    if job is not None and job.state == JobState.cancelled:
        announce_end(store, job_id, "finished: cancelled before it started")
    # The answer shows the outcome when the process ends quickly (it usually does, within a second).
    return JobOut.from_job(_wait_while_running(store, job_id, settings.cancel_grace_seconds + 1.0) or job)


@router.post(
    "/{job_id}/retry",
    response_model=JobOut,
    status_code=202,
    responses={**NOT_FOUND, **NO_SPACE, 409: {"model": ErrorOut}},
    dependencies=[Depends(require_disk_space)],
    summary="Run a failed or cancelled job again with the same inputs (a new job)",
)
def retry_job(
    job_id: JobIdPath, response: Response, store: StoreDep, executor: ExecutorDep, settings: SettingsDep
) -> JobOut:
    job = find_job(store, job_id)
    if job.state not in (JobState.failed, JobState.cancelled):
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"only failed or cancelled jobs can be retried; job {job_id} is {job.state}",
        )
    if job.source_job_id and store.get(job.source_job_id) is None:
        raise HTTPException(status.HTTP_409_CONFLICT, f"the job's source {job.source_job_id} was deleted")
    from service.db import new_job_id

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
    return accepted(response, JobOut.from_job(retry))


@router.delete(
    "/{job_id}",
    status_code=204,
    responses=NOT_FOUND,
    response_class=Response,
    summary="Delete a job and its files (a running job is cancelled first)",
)
def delete_job(job_id: JobIdPath, store: StoreDep, executor: ExecutorDep, settings: SettingsDep) -> Response:
    job = find_job(store, job_id)
    if job.state not in TERMINAL_STATES:
        store.request_cancel(job_id)
        executor.cancel(job_id)
        _wait_while_running(store, job_id, DELETE_WAIT_SECONDS)
    delete_job_and_files(store, settings, job_id)
    return Response(status_code=204)


@router.put(
    "/{job_id}/pin",
    response_model=JobOut,
    responses=NOT_FOUND,
    summary="Keep a job and its files past SFMNERF_JOB_RETENTION_MINUTES",
)
def pin_job(job_id: JobIdPath, store: StoreDep) -> JobOut:
    find_job(store, job_id)
    return JobOut.from_job(store.set_pinned(job_id, True))


@router.delete(
    "/{job_id}/pin",
    response_model=JobOut,
    responses=NOT_FOUND,
    summary="Let a finished job expire again (SFMNERF_JOB_RETENTION_MINUTES after it ended)",
)
def unpin_job(job_id: JobIdPath, store: StoreDep) -> JobOut:
    find_job(store, job_id)
    return JobOut.from_job(store.set_pinned(job_id, False))


def _wait_while_running(store: JobStore, job_id: str, seconds: float) -> Job | None:
    """The job once it is no longer running, or as it is after `seconds`."""
    deadline = time.monotonic() + seconds
    while (job := store.get(job_id)) is not None and job.state == JobState.running:
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)
    return job


def _link_or_copy(source: str, target: str) -> None:
    import os

    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
