"""FastAPI dependencies shared by the routers: settings, store, executor, auth, job look-ups."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.auth import ANONYMOUS, Client
from service.db import Job, JobKind, JobStore
from service.executor import Executor
from service.settings import ServiceSettings

_bearer = HTTPBearer(
    auto_error=False, description="API token (SFMNERF_API_TOKEN or a client's), when configured."
)


def get_settings(request: Request) -> ServiceSettings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_executor(request: Request) -> Executor:
    return request.app.state.executor


SettingsDep = Annotated[ServiceSettings, Depends(get_settings)]
StoreDep = Annotated[JobStore, Depends(get_store)]
ExecutorDep = Annotated[Executor, Depends(get_executor)]
JobIdPath = Annotated[
    str, Path(description="Job id.", examples=["3f2b8c1d9e7a4b6c8d0e1f2a3b4c5d6e"], max_length=64)
]


def current_client(
    request: Request,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)] = None,
) -> Client:
    """The caller, identified by `AuthMiddleware` (the bearer scheme is declared for the OpenAPI docs)."""
    return request.state.client


ClientDep = Annotated[Client, Depends(current_client)]


def visible_job(request: Request, store: StoreDep, client: ClientDep) -> None:
    """404 on every route of a job the caller may not see, exactly as for a job that does not exist."""
    job_id = request.path_params.get("job_id")
    if job_id is None or client.admin:
        return
    job = store.get(job_id)
    if job is None or not client.may_see(job.owner):
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} not found")


def find_job(store: JobStore, job_id: str, kind: JobKind | None = None, client: Client = ANONYMOUS) -> Job:
    """The job, or 404 naming the id (also when it is of another kind or not the client's)."""
    job = store.get(job_id)
    if job is None or (kind is not None and job.kind != kind) or not client.may_see(job.owner):
        what = f"{kind} job" if kind else "job"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"{what} {job_id} not found")
    return job
