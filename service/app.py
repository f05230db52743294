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

from service import openapi
from service.auth import AuthMiddleware
from service.child_processes import reap_leftovers
from service.deps import SettingsDep, StoreDep, current_client, visible_job
from service.errors import ServiceError
from service.executor import make_executor
from service.http_limits import BodyLimits
from service.kinds import JobState
from service.renders import RenderQueue
from service.routes import jobs, nerf, previews, reconstructions, scenes, web
from service.scene_supervisor import SceneSteps, SceneSupervisor
from service.schemas import HealthOut, InfoOut, ReadyOut
from service.security_headers import SecurityHeaders, TrustedHosts
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.uploads import sweep_orphan_folders, without_server_paths
from service.webhooks import WebhookSender

log = logging.getLogger(__name__)


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


def create_app(settings: ServiceSettings | None = None) -> FastAPI:
    """The service: routes, job store and executor (started and stopped with the app's lifespan)."""
    settings = settings or ServiceSettings()
    settings.jobs_dir.mkdir(parents=True, exist_ok=True)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        reap_leftovers(settings.data_dir)  # render and validation processes of a killed API
        store = JobStore(settings.resolved_database_url)  # applies the schema migrations
        sweep_orphan_folders(settings.jobs_dir, store)
        executor = make_executor(settings, store)
        app.state.store, app.state.executor = store, executor
        app.state.renders = RenderQueue(settings)
        scene_supervisor = SceneSupervisor(SceneSteps(store, executor, settings))
        webhook_sender = WebhookSender(store, settings)
        executor.start()
        scene_supervisor.start()
        webhook_sender.start()
        try:
            yield
        finally:
            webhook_sender.stop()
            scene_supervisor.stop()
            app.state.renders.stop()
            executor.stop()
            store.dispose()

    app = FastAPI(
        title="sfmnerf",
        version=_package_version(),
        description="Photographs to 3D: Structure from Motion reconstructions and Neural Radiance Field "
        "training as jobs, with their artifacts and renders.",
        lifespan=lifespan,
        generate_unique_id_function=openapi.operation_id,
        **({"docs_url": None, "redoc_url": None, "openapi_url": None} if settings.docs == "off" else {}),
    )
    app.state.settings = settings
    # The last added runs first: the Host, then the token, are checked before the body limit and before any
    # body is read.
    app.add_middleware(BodyLimits, settings=settings)
    app.add_middleware(AuthMiddleware, settings=settings)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(TrustedHosts, settings=settings)

    @app.exception_handler(ServiceError)
    async def _refused(_request: Request, error: ServiceError) -> JSONResponse:
        detail = without_server_paths(error.detail, settings)  # the last guard; messages name uploads
        return JSONResponse({"detail": detail}, status_code=error.status_code, headers=error.headers)

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
        dependencies=[Depends(current_client)],
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

    for router in (jobs.router, reconstructions.router, nerf.router, previews.router, scenes.router):
        app.include_router(router, dependencies=[Depends(visible_job)])
    web.mount(app)
    openapi.install(app)
    return app
