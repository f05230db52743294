"""/v1/nerf: train a radiance field, follow its metrics, download checkpoints, render views and videos."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import (
    APIRouter,
    Depends,
    File,
    Form,
    HTTPException,
    Query,
    Request,
    Response,
    UploadFile,
    status,
)
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from neural.config import ModelName
from service.actions.jobs import find_job
from service.actions.nerf import (
    NerfInputs,
    TrainOptions,
    camera_path_of,
    check_render_size,
    require_checkpoint,
    run_checkpoints,
)
from service.actions.nerf import create_nerf as create
from service.actions.nerf import queue_video as queue
from service.deps import ClientDep, ExecutorDep, JobIdPath, SettingsDep, StoreDep, require_disk_space
from service.kinds import JobKind, JobState
from service.layout import RUN_CONFIG, RUN_METRICS, job_dir, output_dir
from service.openapi import file_response
from service.renders import RenderBusy, RenderFailed, RenderSpec, spec_from_request
from service.routes.common import NEW_WORK_REFUSED, NOT_FOUND, REJECTED, accepted, input_file
from service.runner import finite_or_none
from service.schemas import (
    CameraPathOut,
    CheckpointOut,
    ErrorOut,
    JobOut,
    MetricPoint,
    NerfOut,
    RenderRequest,
    VideoRequest,
)
from service.settings import ServiceSettings

router = APIRouter(prefix="/v1/nerf", tags=["nerf"])
NO_CHECKPOINT = {409: {"model": ErrorOut, "description": "The job has no checkpoint yet."}}
PNG = file_response("image/png", description="The rendered view.")


@router.post(
    "",
    response_model=JobOut,
    status_code=202,
    responses={**REJECTED, **NOT_FOUND, **NEW_WORK_REFUSED},
    dependencies=[Depends(require_disk_space)],
    summary="Train a NeRF on an uploaded dataset (Blender zip or .npz) or a reconstruction",
)
def create_nerf(
    response: Response,
    store: StoreDep,
    client: ClientDep,
    executor: ExecutorDep,
    settings: SettingsDep,
    dataset: Annotated[
        UploadFile | None,
        File(
            description="A zip of a Blender-format dataset (transforms_train.json + images) "
            "or a tiny-NeRF .npz."
        ),
    ] = None,
    reconstruction_id: Annotated[
        str | None,
        Form(max_length=64, description="Train on this finished reconstruction instead of an upload."),
    ] = None,
    model: Annotated[ModelName, Form()] = "fast",
    steps: Annotated[int | None, Form(ge=1, le=10_000_000, examples=[2000])] = None,
    minutes: Annotated[float | None, Form(gt=0, le=100_000, examples=[10.0])] = None,
    batch_rays: Annotated[int | None, Form(ge=1, le=1_000_000, examples=[1024])] = None,
    device: Annotated[Literal["auto", "cpu", "cuda"] | None, Form()] = None,
    options: Annotated[
        str | None,
        Form(
            max_length=20_000,
            description="More TrainConfig fields as a JSON object.",
            examples=['{"checkpoint_every": 500}'],
        ),
    ] = None,
    webhook_url: Annotated[str | None, Form(pattern=r"^https?://\S+$", max_length=2000)] = None,
) -> JobOut:
    inputs = NerfInputs(
        train=TrainOptions(
            model=model, steps=steps, minutes=minutes, batch_rays=batch_rays, device=device, options=options
        ),
        dataset=input_file(dataset), reconstruction_id=reconstruction_id, webhook_url=webhook_url,
    )  # fmt: skip
    return accepted(response, JobOut.from_job(create(store, executor, settings, client, inputs)))


def _read_metrics(path: Path) -> list[MetricPoint]:
    """metrics.jsonl so far; a line being written (no newline yet) is skipped."""
    if not path.is_file():
        return []
    points = []
    for line in path.read_text().splitlines():
        try:
            record = {key: finite_or_none(value) for key, value in json.loads(line).items()}
            points.append(MetricPoint.model_validate(record))
        except ValueError:
            continue
    return points


@router.get(
    "/{job_id}",
    response_model=NerfOut,
    responses=NOT_FOUND,
    summary="A NeRF job with its metrics so far (step, loss, PSNR)",
)
def get_nerf(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> NerfOut:
    job = find_job(store, job_id, JobKind.nerf)
    run_dir = output_dir(settings, job_id)
    config_path = run_dir / RUN_CONFIG
    try:
        config = (
            json.loads(config_path.read_text()) if config_path.is_file() else job.params.get("train_config")
        )
    except ValueError:
        config = job.params.get("train_config")
    checkpoints = run_checkpoints(run_dir)
    base = f"/v1/nerf/{job_id}"
    return NerfOut(
        job=JobOut.from_job(job),
        config=config,
        metrics=_read_metrics(run_dir / RUN_METRICS),
        latest_step=checkpoints[-1].step if checkpoints else None,
        links={
            "checkpoints": f"{base}/checkpoints",
            "render": f"{base}/render",
            "video": f"{base}/video",
            "camera_path": f"{base}/camera-path",
        },
    )


@router.get(
    "/{job_id}/checkpoints",
    response_model=list[CheckpointOut],
    responses=NOT_FOUND,
    summary="The checkpoints kept so far",
)
def get_checkpoints(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> list[CheckpointOut]:
    find_job(store, job_id, JobKind.nerf)
    return [
        CheckpointOut(
            step=c.step,
            is_latest=c.is_latest,
            is_best=c.is_best,
            val_psnr=finite_or_none(c.val_psnr),
            size_bytes=Path(c.path).stat().st_size,
            url=f"/v1/nerf/{job_id}/checkpoints/{c.step}",
        )
        for c in run_checkpoints(output_dir(settings, job_id))
        if Path(c.path).is_file()
    ]


@router.get(
    "/{job_id}/checkpoints/{step}",
    response_class=FileResponse,
    responses={**NOT_FOUND, **file_response("application/octet-stream", description="PyTorch file.")},
    summary="Download one checkpoint (a PyTorch file)",
)
def download_checkpoint(job_id: JobIdPath, step: int, store: StoreDep, settings: SettingsDep) -> FileResponse:
    find_job(store, job_id, JobKind.nerf)
    for checkpoint in run_checkpoints(output_dir(settings, job_id)):
        if checkpoint.step == step and Path(checkpoint.path).is_file():
            return FileResponse(
                checkpoint.path, media_type="application/octet-stream", filename=Path(checkpoint.path).name
            )
    raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} has no checkpoint at step {step}")


def _render_spec(store: Any, settings: ServiceSettings, job_id: str, request: RenderRequest) -> RenderSpec:
    """The view to render, its checkpoint resolved to a step (the render cache's key); 4xx otherwise."""
    find_job(store, job_id, JobKind.nerf)
    check_render_size(request.width * request.height, settings)
    run_dir = require_checkpoint(job_id, settings)
    checkpoints = run_checkpoints(run_dir)
    which = request.checkpoint
    for checkpoint in checkpoints:
        if (
            (which == "latest" and checkpoint.is_latest)
            or (which == "best" and checkpoint.is_best)
            or (which == checkpoint.step)
        ):
            return spec_from_request(job_id, run_dir, checkpoint.step, request)
    raise HTTPException(
        422, f"checkpoint: no checkpoint {which!r} (have steps {[c.step for c in checkpoints]})"
    )


@router.get(
    "/{job_id}/camera-path",
    response_model=CameraPathOut,
    responses={
        **NOT_FOUND,
        409: {"model": ErrorOut, "description": "Training has not started yet."},
        422: {"model": ErrorOut, "description": "The run records no registered cameras."},
    },
    summary="How the photos were taken: the default view and a camera path through the cameras",
)
def get_camera_path(
    job_id: JobIdPath,
    store: StoreDep,
    settings: SettingsDep,
    num_frames: Annotated[int, Query(ge=1, le=720)] = 36,
) -> CameraPathOut:
    return CameraPathOut(**camera_path_of(store, settings, job_id, num_frames))


@router.post(
    "/{job_id}/render",
    response_class=Response,
    responses={
        **PNG,
        **NOT_FOUND,
        **NO_CHECKPOINT,
        503: {"model": ErrorOut, "description": "Every render slot is busy: retry after Retry-After s."},
    },
    summary="Render a view from the latest (or a chosen) checkpoint; works while training",
)
async def render(
    job_id: JobIdPath, request: RenderRequest, http: Request, store: StoreDep, settings: SettingsDep
) -> Response:
    # Runs on the event loop: the checks go to a thread, the render to a render process.
    spec = await run_in_threadpool(_render_spec, store, settings, job_id, request)
    try:
        png = await http.app.state.renders.render(spec)
    except RenderBusy as busy:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            f"all {settings.render_queue_size} render slots are busy (SFMNERF_RENDER_QUEUE_SIZE); "
            f"retry after {busy.retry_after} s",
            headers={"Retry-After": str(busy.retry_after)},
        ) from None
    except RenderFailed as failed:
        raise HTTPException(failed.status_code, failed.detail) from None
    return Response(png, media_type="image/png")


@router.post(
    "/{job_id}/video",
    response_model=JobOut,
    status_code=202,
    responses={
        **NOT_FOUND,
        **NO_CHECKPOINT,
        **NEW_WORK_REFUSED,
        413: {"model": ErrorOut, "description": "Over the video budget SFMNERF_MAX_VIDEO_PIXELS."},
    },
    dependencies=[Depends(require_disk_space)],
    summary="Queue an orbit video of the latest checkpoint",
)
def queue_video(
    job_id: JobIdPath,
    request: VideoRequest,
    response: Response,
    store: StoreDep,
    executor: ExecutorDep,
    settings: SettingsDep,
) -> JobOut:
    return accepted(response, JobOut.from_job(queue(store, executor, settings, job_id, request)))


@router.get(
    "/{job_id}/video",
    response_class=FileResponse,
    responses={
        **NOT_FOUND,
        409: {"model": ErrorOut, "description": "The video is not ready."},
        **file_response("image/gif", "video/mp4", description="The video."),
    },
    summary="The latest finished orbit video",
)
def get_video(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    find_job(store, job_id, JobKind.nerf)
    videos = store.jobs_with_source(job_id, JobKind.video)
    if not videos:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no video was queued for NeRF job {job_id}")
    for video in videos:  # newest first
        if video.state == JobState.succeeded and video.result and "file" in video.result:
            path = job_dir(settings, video.id) / video.result["file"]
            if path.is_file():
                media = {".gif": "image/gif", ".mp4": "video/mp4"}.get(
                    path.suffix, "application/octet-stream"
                )
                return FileResponse(path, media_type=media, filename=path.name)
    raise HTTPException(
        status.HTTP_409_CONFLICT,
        f"the latest video job {videos[0].id} is {videos[0].state}"
        + (f": {videos[0].error}" if videos[0].error else ""),
    )
