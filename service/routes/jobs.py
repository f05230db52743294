"""/v1/jobs: list, inspect, follow logs, cancel, retry and delete jobs of every kind."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response

from service.actions.jobs import cancel_job as cancel
from service.actions.jobs import delete_job as delete
from service.actions.jobs import find_job
from service.actions.jobs import retry_job as retry
from service.deps import ClientDep, ExecutorDep, JobIdPath, SettingsDep, StoreDep, require_disk_space
from service.kinds import JobKind, JobState
from service.routes.common import MAX_PAGE, NEW_WORK_REFUSED, NOT_FOUND, accepted
from service.schemas import ErrorOut, JobList, JobOut, LogsOut

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
MAX_LOG_LINES = 5000


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
    return JobOut.from_job(cancel(store, executor, settings, job_id))


@router.post(
    "/{job_id}/retry",
    response_model=JobOut,
    status_code=202,
    responses={**NOT_FOUND, **NEW_WORK_REFUSED, 409: {"model": ErrorOut}},
    dependencies=[Depends(require_disk_space)],
    summary="Run a failed or cancelled job again with the same inputs (a new job)",
)
def retry_job(
    job_id: JobIdPath, response: Response, store: StoreDep, executor: ExecutorDep, settings: SettingsDep
) -> JobOut:
    return accepted(response, JobOut.from_job(retry(store, executor, settings, job_id)))


@router.delete(
    "/{job_id}",
    status_code=204,
    responses=NOT_FOUND,
    response_class=Response,
    summary="Delete a job and its files (a running job is cancelled first)",
)
def delete_job(job_id: JobIdPath, store: StoreDep, executor: ExecutorDep, settings: SettingsDep) -> Response:
    delete(store, executor, settings, job_id)
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
