"""FastAPI dependencies shared by the routers: settings, store, executor, the caller, what it may see, disk
space and the caller's quotas for new work."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.auth import Client
from service.errors import no_space
from service.executor import Executor
from service.housekeeping import disk_space_problem
from service.quotas import check_client_quota
from service.settings import ServiceSettings
from service.store.job_store import JobStore

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


def require_disk_space(settings: SettingsDep, store: StoreDep, client: ClientDep) -> None:
    """507 Insufficient Storage for new work while the disk is below SFMNERF_MIN_FREE_DISK_BYTES; the
    client's quotas (service.quotas): 429 or 507."""
    if (problem := disk_space_problem(settings)) is not None:
        raise no_space(problem)
    check_client_quota(store, client, settings)
