"""Renders off the API process: long-lived render processes behind a bounded queue, and a render cache.

`RenderQueue.render` never runs a render in the API: it hands the request to one of
SFMNERF_RENDER_WORKERS processes (spawned on the first render; each keeps the models it loaded, so
repeated renders of one checkpoint skip the load) and awaits the answer without blocking the event loop.
At most SFMNERF_RENDER_QUEUE_SIZE renders wait or run at once; the next gets 503 with Retry-After.
With executor=celery the render runs as a Celery task instead and the answer is the PNG it writes into
the shared data folder. Identical requests (job, checkpoint step, camera, size) are answered from the
job's render cache (`renders/` in the job folder, the newest SFMNERF_RENDER_CACHE_PER_JOB kept).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import hashlib
import io
import json
import logging
import multiprocessing
import os
import uuid
from collections import OrderedDict
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from service.celery_config import RENDER_TASK, make_celery
from service.settings import ServiceSettings

logger = logging.getLogger(__name__)
CACHE_DIR = "renders"
MODELS_KEPT_PER_PROCESS = 2
RETRY_AFTER_SECONDS = 2
CELERY_POLL_SECONDS = 0.05
UNEXPECTED_RENDER_ERROR = "the render failed on the worker; its log has the reason"


class RenderBusy(Exception):
    """Every render slot is taken; the client should come back after `retry_after` seconds."""

    retry_after = RETRY_AFTER_SECONDS


class RenderFailed(Exception):
    """The render could not be made: a message for the client (422), or the worker died (503)."""

    def __init__(self, detail: str, status_code: int = 422) -> None:
        super().__init__(detail)
        self.detail, self.status_code = detail, status_code


@dataclass(frozen=True)
class RenderSpec:
    """One view of one checkpoint: what a render process needs and what identifies the image."""

    job_id: str
    run_dir: str
    which: str
    """The checkpoint asked for: "latest", "best" or a step."""
    step: int
    """The step `which` named when the request came in (the trainer may have saved a newer one since)."""
    c2w: tuple[tuple[float, ...], ...] | None
    """None: the run's default view."""
    frame: str
    """How c2w is read: "auto", "capture" or "data" (neural.inference.PoseFrame)."""
    width: int
    height: int
    fx: float | None
    fov_x: float | None
    allow_empty_view: bool = False
    """Return a view that sees nothing of the scene instead of refusing it (RenderFailed, 422)."""

    def cache_key(self) -> str:
        fields = {k: v for k, v in asdict(self).items() if k not in ("run_dir", "which")}
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:32]


# ---- inside a render process ----------------------------------------------------------------------------

_models: OrderedDict[tuple[str, int, int], Any] = OrderedDict()


def _init_render_process(threads: int, parent_pid: int, data_dir: str) -> None:
    import torch

    from service.child_processes import become_child_of

    become_child_of(parent_pid, Path(data_dir))

    torch.set_num_threads(threads)


def _loaded_run(run_dir: str, which: str) -> Any:
    """The run restored from checkpoint `which`, from this process's small LRU of loaded models."""
    from neural.checkpoints import resolve_checkpoint
    from neural.errors import CheckpointError
    from neural.inference import load_run

    try:
        path = resolve_checkpoint(Path(run_dir), which)
        key = (str(path), path.stat().st_mtime_ns)
    except (CheckpointError, OSError):  # the trainer replaced it just now: load_run resolves again
        key = None
    if key is None or key not in _models:
        run = load_run(run_dir, which, device="auto")
        if key is None:
            return run
        _models[key] = run
        while len(_models) > MODELS_KEPT_PER_PROCESS:
            _models.popitem(last=False)
    _models.move_to_end(key)
    return _models[key]


def render_png(spec: RenderSpec, cache_dir: str | None = None) -> bytes:
    """The PNG of the view; kept in cache_dir (atomically, under the step really rendered) when given.
    Raises RenderFailed."""
    import numpy as np
    from PIL import Image

    from neural.camera_path import CameraPathError
    from neural.errors import CheckpointError
    from neural.inference import EmptyViewError, check_sees_scene, render_frame, to_uint8, view_camera

    try:
        run = _loaded_run(spec.run_dir, spec.which)
    except CheckpointError as error:
        raise RenderFailed(f"checkpoint: {str(error).replace(spec.run_dir, 'the run')}") from None
    camera = view_camera(run, spec.width, spec.height, spec.fx, spec.fov_x)
    c2w = None if spec.c2w is None else np.asarray(spec.c2w, dtype=float)
    try:
        rendered = render_frame(run, c2w, camera, spec.frame)
        pixels = to_uint8((rendered if spec.allow_empty_view else check_sees_scene(rendered)).rgb)
    except (CameraPathError, EmptyViewError) as error:
        raise RenderFailed(str(error)) from None
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    png = buffer.getvalue()
    if cache_dir is not None:
        _write_atomically(Path(cache_dir) / f"{replace(spec, step=run.step).cache_key()}.png", png)
    return png


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.{uuid.uuid4().hex}.partial")
    partial.write_bytes(data)
    partial.replace(path)


def run_render_task(spec: dict, out_path: str, error_path: str, cache_dir: str | None) -> None:
    """The Celery render task: the PNG (or the error message) lands in the shared data folder."""
    try:
        c2w = None if spec["c2w"] is None else tuple(map(tuple, spec["c2w"]))
        png = render_png(RenderSpec(**{**spec, "c2w": c2w}), cache_dir)
        _write_atomically(Path(out_path), png)
    except RenderFailed as error:
        _write_render_error(Path(error_path), error)
    except Exception:  # the API waits for an answer file: without one it would wait out its timeout
        logger.exception("render of job %s failed", spec.get("job_id"))
        _write_render_error(Path(error_path), RenderFailed(UNEXPECTED_RENDER_ERROR, 500))


def _write_render_error(path: Path, error: RenderFailed) -> None:
    _write_atomically(path, json.dumps({"detail": error.detail, "status_code": error.status_code}).encode())


def read_render_error(path: Path) -> RenderFailed:
    answer = json.loads(path.read_text())
    return RenderFailed(answer["detail"], answer["status_code"])


# ---- in the API process ------------------------------------------------------------------------------------


class RenderQueue:
    """Bounded hand-off of renders to render processes (local) or Celery; plus the render cache."""

    def __init__(self, settings: ServiceSettings) -> None:
        self.settings = settings
        self._in_flight = 0  # touched only on the event loop
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._celery: Any = None

    def stop(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def cache_dir(self, spec: RenderSpec) -> Path | None:
        """Where a job's renders are kept; None when the cache is off."""
        if self.settings.render_cache_per_job == 0:
            return None
        return self.settings.jobs_dir / spec.job_id / CACHE_DIR

    def cached(self, spec: RenderSpec) -> bytes | None:
        if (folder := self.cache_dir(spec)) is None:
            return None
        try:
            return (folder / f"{spec.cache_key()}.png").read_bytes()
        except OSError:
            return None

    async def render(self, spec: RenderSpec) -> bytes:
        """The PNG of the view: from the cache, or rendered in a worker. RenderBusy when the queue is full."""
        if (png := self.cached(spec)) is not None:
            return png
        if self._in_flight >= self.settings.render_queue_size:
            raise RenderBusy
        self._in_flight += 1
        cache_dir = self.cache_dir(spec)
        try:
            if self.settings.executor == "celery":
                png = await self._render_with_celery(spec, cache_dir)
            else:
                png = await self._render_locally(spec, cache_dir)
        finally:
            self._in_flight -= 1
        if cache_dir is not None:
            await asyncio.to_thread(self._trim_cache, cache_dir)
        return png

    async def _render_locally(self, spec: RenderSpec, cache_dir: Path | None) -> bytes:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=self.settings.render_workers,
                mp_context=multiprocessing.get_context("spawn"),  # never fork a threaded server
                initializer=_init_render_process,
                initargs=(self.settings.threads_per_job(), os.getpid(), str(self.settings.data_dir)),
            )
        future = self._pool.submit(render_png, spec, str(cache_dir) if cache_dir else None)
        try:
            return await asyncio.wait_for(asyncio.wrap_future(future), self.settings.render_timeout_seconds)
        except concurrent.futures.process.BrokenProcessPool:
            self.stop()  # a render process died (out of memory?): the next render starts a fresh pool
            raise RenderFailed("the render process died; try again or ask for a smaller image", 503) from None
        except TimeoutError:
            raise RenderFailed(
                f"the render took longer than SFMNERF_RENDER_TIMEOUT_SECONDS="
                f"{self.settings.render_timeout_seconds:g}",
                504,
            ) from None

    async def _render_with_celery(self, spec: RenderSpec, cache_dir: Path | None) -> bytes:
        if self._celery is None:
            self._celery = make_celery(self.settings)
        out_path = self.settings.jobs_dir / spec.job_id / "render-answers" / f"{uuid.uuid4().hex}.png"
        error_path = out_path.with_suffix(".error")
        self._celery.send_task(
            RENDER_TASK,
            args=[asdict(spec), str(out_path), str(error_path), str(cache_dir) if cache_dir else None],
            expires=self.settings.render_timeout_seconds,
            time_limit=self.settings.render_timeout_seconds,
        )
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.settings.render_timeout_seconds
        try:
            while loop.time() < deadline:
                if out_path.is_file():
                    return out_path.read_bytes()
                if error_path.is_file():
                    raise read_render_error(error_path)
                await asyncio.sleep(CELERY_POLL_SECONDS)
        finally:
            for path in (out_path, error_path):
                path.unlink(missing_ok=True)
        raise RenderFailed(
            f"no Celery worker rendered the view within SFMNERF_RENDER_TIMEOUT_SECONDS="
            f"{self.settings.render_timeout_seconds:g}",
            504,
        )

    def _trim_cache(self, folder: Path) -> None:
        """Keeps the newest SFMNERF_RENDER_CACHE_PER_JOB renders of a job."""
        try:
            files = sorted(folder.glob("*.png"), key=lambda p: p.stat().st_mtime_ns, reverse=True)
        except OSError:
            return
        for path in files[self.settings.render_cache_per_job :]:
            path.unlink(missing_ok=True)


def spec_from_request(job_id: str, run_dir: Path, step: int, request: Any) -> RenderSpec:
    """The RenderSpec of a RenderRequest (service.schemas) whose checkpoint is at `step` right now."""
    import math

    c2w = request.camera_to_world()
    return RenderSpec(
        job_id=job_id,
        run_dir=os.fspath(run_dir),
        which=str(request.checkpoint),
        step=step,
        c2w=None if c2w is None else tuple(tuple(float(v) for v in row) for row in c2w),
        frame=request.frame,
        width=request.width,
        height=request.height,
        fx=request.fx,
        fov_x=math.radians(request.fov_x_deg) if request.fov_x_deg is not None else None,
        allow_empty_view=request.allow_empty_view,
    )
