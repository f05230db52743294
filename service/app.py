"""The FastAPI application: `create_app(settings)` wires the job store, the executor and the /v1 routes."""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.db import JobState, JobStore
from service.deps import SettingsDep, StoreDep, require_token
from service.executor import make_executor
from service.models import HealthOut, InfoOut, ReadyOut
from service.renders import RenderQueue
from service.routes import jobs, nerf, reconstructions
from service.settings import ServiceSettings
from service.uploads import UploadRejected

log = logging.getLogger(__name__)


class BodySizeLimit:
    """Answers 413 to request bodies above the limit, declared (Content-Length) or streamed."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    def _detail(self) -> str:
        return f"the request body is larger than the limit SFMNERF_MAX_UPLOAD_BYTES={self.max_bytes}"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            await JSONResponse({"detail": self._detail()}, status_code=413)(scope, receive, send)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # An HTTPException passes FastAPI's body parsing unchanged and becomes the response.
                    raise StarletteHTTPException(413, self._detail())
            return message

        await self.app(scope, limited_receive, send)


@cache
def _torch_device() -> str:
    try:
        import torch
    except ImportError:
        return "unavailable (torch not installed)"
    if torch.cuda.is_available():
        return f"cuda ({torch.cuda.get_device_name(0)})"
    return "cpu"


def _package_version() -> str:
    try:
        return version("sfmnerf")
    except PackageNotFoundError:
        return "unknown"


JOB_OPERATIONS = {
    "GetJob": ("get", "/v1/jobs/{job_id}"),
    "GetLogs": ("get", "/v1/jobs/{job_id}/logs"),
    "CancelJob": ("post", "/v1/jobs/{job_id}/cancel"),
    "RetryJob": ("post", "/v1/jobs/{job_id}/retry"),
    "PinJob": ("put", "/v1/jobs/{job_id}/pin"),
    "UnpinJob": ("delete", "/v1/jobs/{job_id}/pin"),
    "DeleteJob": ("delete", "/v1/jobs/{job_id}"),
}
"""What a client can do with a job id an answer gave it (OpenAPI links, followed by clients and fuzzers)."""
JOB_ID_SOURCES = {
    ("post", "/v1/reconstructions", "202"): "$response.body#/id",
    ("post", "/v1/nerf", "202"): "$response.body#/id",
    ("post", "/v1/nerf/{job_id}/video", "202"): "$response.body#/id",
    ("post", "/v1/jobs/{job_id}/retry", "202"): "$response.body#/id",
    ("post", "/v1/jobs/{job_id}/cancel", "200"): "$response.body#/id",
    ("get", "/v1/jobs/{job_id}", "200"): "$response.body#/id",
    ("put", "/v1/jobs/{job_id}/pin", "200"): "$response.body#/id",
    ("get", "/v1/jobs", "200"): "$response.body#/items/0/id",
}


def add_job_links(schema: dict[str, Any]) -> dict[str, Any]:
    """Adds OpenAPI links from every answer that names a job to the operations on that job."""
    paths = schema["paths"]
    for (method, path, code), source in JOB_ID_SOURCES.items():
        response = paths[path][method]["responses"][code]
        response["links"] = {
            name: {"operationId": paths[target][verb]["operationId"], "parameters": {"job_id": source}}
            for name, (verb, target) in JOB_OPERATIONS.items()
        }
    return schema


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """The service: routes, job store and executor (started and stopped with the app's lifespan)."""
    settings = settings or ServiceSettings()
    settings.jobs_dir.mkdir(parents=True, exist_ok=True)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = JobStore(settings.resolved_database_url)  # applies the schema migrations
        executor = make_executor(settings, store)
        app.state.store, app.state.executor = store, executor
        app.state.renders = RenderQueue(settings)
        executor.start()
        try:
            yield
        finally:
            app.state.renders.stop()
            executor.stop()
            store.dispose()

    app = FastAPI(
        title="sfmnerf",
        version=_package_version(),
        description="Photographs to 3D: Structure from Motion reconstructions and Neural Radiance Field "
        "training as jobs, with their artifacts and renders.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes)

    @app.exception_handler(UploadRejected)
    async def _rejected(_request: Request, error: UploadRejected) -> JSONResponse:
        return JSONResponse({"detail": error.detail}, status_code=error.status_code)

    @app.exception_handler(json.JSONDecodeError)
    async def _bad_json(_request: Request, error: json.JSONDecodeError) -> JSONResponse:
        return JSONResponse({"detail": f"body: not valid JSON ({error})"}, status_code=422)

    @app.get("/healthz", response_model=HealthOut, tags=["health"], summary="The process is alive")
    def healthz() -> HealthOut:
        return HealthOut(status="ok")

    @app.get(
        "/readyz",
        response_model=ReadyOut,
        tags=["health"],
        responses={503: {"model": ReadyOut, "description": "The database or the queue is unreachable."}},
        summary="The database and the job queue are reachable",
    )
    def readyz(request: Request, store: StoreDep) -> Any:
        try:
            store.ping()
            database = "ok"
        except Exception as error:  # any driver error means not ready
            database = f"unreachable ({type(error).__name__})"
        queue = request.app.state.executor.problem() or "ok"
        ready = database == "ok" and queue == "ok"
        body = ReadyOut(status="ready" if ready else "not ready", database=database, queue=queue)
        return body if ready else JSONResponse(body.model_dump(), status_code=503)

    @app.get(
        "/v1/info",
        response_model=InfoOut,
        tags=["health"],
        dependencies=[Depends(require_token)],
        summary="Version, device, queue length and limits",
    )
    def info(store: StoreDep, current: SettingsDep) -> InfoOut:
        return InfoOut(
            version=_package_version(),
            executor=current.executor,
            device=_torch_device(),
            queue_length=store.count(JobState.queued),
            running=store.count(JobState.running),
            concurrency=current.concurrency,
            limits=current.limits(),
        )

    for router in (jobs.router, reconstructions.router, nerf.router):
        app.include_router(router, dependencies=[Depends(require_token)])

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = add_job_links(FastAPI.openapi(app))
        return app.openapi_schema

    app.openapi = openapi
    return app
