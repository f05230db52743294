"""FastAPI dependencies shared by the routers: settings, store, executor, auth, job look-ups."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.db import Job, JobKind, JobStore
from service.executor import Executor
from service.settings import ServiceSettings

_bearer = HTTPBearer(auto_error=False, description="API token (SFMNERF_API_TOKEN), when configured.")


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


def require_token(
    settings: SettingsDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> None:
    """Every /v1 route needs `Authorization: Bearer TOKEN` when SFMNERF_API_TOKEN is set."""
    if settings.api_token is None:
        return
    expected = settings.api_token.get_secret_value()
    if credentials is None or not secrets.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or wrong API token (Authorization: Bearer TOKEN)",
            headers={"WWW-Authenticate": "Bearer"},
        )


def find_job(store: JobStore, job_id: str, kind: JobKind | None = None) -> Job:
    """The job, or 404 naming the id (also when it exists but is of another kind)."""
    job = store.get(job_id)
    if job is None or (kind is not None and job.kind != kind):
        what = f"{kind} job" if kind else "job"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"{what} {job_id} not found")
    return job
