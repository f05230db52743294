"""/v1/scenes: photos in, novel views out; one resource over a reconstruction, a NeRF and its renders."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path
from typing import Annotated, Literal

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
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from neural.budget import VIEWS_SHARE
from service.actions.nerf import TrainOptions
from service.actions.reconstructions import ReconstructionInputs
from service.actions.scenes import SceneInputs, scene_lock, scene_owner, stage_jobs
from service.actions.scenes import cancel_scene as cancel
from service.actions.scenes import create_scene as create
from service.actions.scenes import delete_scene as delete
from service.actions.scenes import retry_scene as retry
from service.deps import ClientDep, ExecutorDep, SettingsDep, StoreDep, require_disk_space
from service.kinds import JobState
from service.layout import RECONSTRUCTION_EXPORTS, output_dir
from service.openapi import file_response
from service.pipeline import DONE, EVALUATION_FILE, STAGE_WEIGHTS, STAGES
from service.routes.common import MAX_PAGE, NEW_WORK_REFUSED, REJECTED, accepted, input_file, input_files
from service.schemas import ErrorOut, JobOut
from service.store.tables import Scene

SCENE_NOT_FOUND = {404: {"model": ErrorOut, "description": "No scene with this id."}}
CONFLICT = {409: {"model": ErrorOut, "description": "Not possible in the scene's state."}}
SceneIdPath = Annotated[str, PathParam(description="Scene id.", max_length=64)]


class SceneStageOut(BaseModel):
    name: Literal["reconstruction", "nerf", "views"]
    state: JobState | Literal["pending"] = Field(..., description="pending: its jobs have not been created.")
    progress: float = Field(..., ge=0, le=1)
    job_ids: list[str] = Field(
        ..., description="The stage's child jobs (views: the video and the evaluation)."
    )


class HeldOutView(BaseModel):
    image: str = Field(..., examples=["3"])
    psnr: float = Field(..., examples=[18.2])
    ssim: float = Field(..., examples=[0.61])
    url: str


class SceneOut(BaseModel):
    """A scene: where it stands, its stages and child jobs, its own log and links to every artifact."""

    id: str
    state: JobState
    stage: Literal["reconstruction", "nerf", "views", "done"]
    progress: float = Field(..., ge=0, le=1, description="Overall fraction done, 0..1 (stages weighted).")
    created_at: datetime
    finished_at: datetime | None = None
    error: str | None = Field(None, description="The stage that failed and why.")
    stages: list[SceneStageOut]
    log: list[str] = Field(..., description="The scene's own events; each child job has its log too.")
    links: dict[str, str] = Field(..., description="Every artifact of both stages (child jobs' routes).")
    held_out: list[HeldOutView] = Field(default_factory=list, description="Renders of the held-out views.")
    held_out_mean_psnr: float | None = None
    expected_seconds: dict[str, float] | None = Field(
        None,
        description="Expected seconds of reconstruction, training, views and in total on a CPU, estimated "
        "when the scene started (a time budget only: minutes).",
        examples=[{"reconstruction": 20.0, "training": 600.0, "views": 120.0, "total": 740.0}],
    )


class SceneList(BaseModel):
    items: list[SceneOut]
    total: int
    limit: int
    offset: int


def _describe(scene: Scene, request: Request) -> SceneOut:
    store, settings = request.app.state.store, request.app.state.settings
    stages, links = [], {"self": f"/v1/scenes/{scene.id}"}
    for name in STAGES:
        jobs = [store.get(job_id) for job_id in stage_jobs(scene, name)]
        jobs = [job for job in jobs if job is not None]
        if not jobs:
            state, progress = "pending", 1.0 if scene.stage == DONE else 0.0
        else:
            states = {JobState(job.state) for job in jobs}
            expected = 2 if name == "views" else 1
            state = next(
                (
                    s
                    for s in (JobState.failed, JobState.cancelled, JobState.running, JobState.queued)
                    if s in states
                ),
                JobState.succeeded if len(jobs) == expected else JobState.running,
            )
            progress = sum(job.progress for job in jobs) / expected
        stages.append(
            SceneStageOut(name=name, state=state, progress=progress, job_ids=[job.id for job in jobs])
        )
        for job in jobs:
            job_links = JobOut.from_job(job).links
            links.update({f"{job.kind}_job": job_links["self"], f"{job.kind}_logs": job_links["logs"]})
            if "result" in job_links:
                links[str(job.kind)] = job_links["result"]
    if scene.reconstruction_job_id:
        base = f"/v1/reconstructions/{scene.reconstruction_job_id}"
        links.update({name: f"{base}/{name}" for name in RECONSTRUCTION_EXPORTS})
    if scene.nerf_job_id:
        base = f"/v1/nerf/{scene.nerf_job_id}"
        links.update(
            render=f"{base}/render", checkpoints=f"{base}/checkpoints", validation=f"{base}/validation"
        )
    held_out, mean_psnr = [], None
    metrics_path = output_dir(settings, scene.evaluation_job_id or "-") / EVALUATION_FILE
    if scene.evaluation_job_id and metrics_path.is_file():
        metrics = json.loads(metrics_path.read_text())
        mean_psnr = metrics["mean_psnr"]
        held_out = [
            HeldOutView(
                image=m["name"],
                psnr=m["psnr"],
                ssim=m["ssim"],
                url=f"/v1/scenes/{scene.id}/held-out/{m['name']}.png",
            )
            for m in metrics["per_image"]
        ]
    return SceneOut(
        id=scene.id,
        state=JobState(scene.state),
        stage=scene.stage,
        progress=sum(STAGE_WEIGHTS[s.name] * s.progress for s in stages),
        created_at=scene.created_at,
        finished_at=scene.finished_at,
        error=scene.error,
        stages=stages,
        log=scene.log,
        links=links,
        held_out=held_out,
        held_out_mean_psnr=mean_psnr,
        expected_seconds=scene.params.get("expected_seconds"),
    )


def _find(request: Request, scene_id: str) -> Scene:
    scene = request.app.state.store.get_scene(scene_id)
    if scene is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id} not found")
    return scene


def visible_scene(request: Request, store: StoreDep, client: ClientDep) -> None:
    """404 on every route of a scene of another client (its reconstruction job's owner), exactly as for a
    scene that does not exist (service.deps.visible_job for scenes)."""
    scene_id = request.path_params.get("scene_id")
    if scene_id is None or client.admin:
        return
    scene = store.get_scene(scene_id)
    if scene is None or not client.may_see(scene_owner(store, scene)):
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id} not found")


router = APIRouter(prefix="/v1/scenes", tags=["scenes"], dependencies=[Depends(visible_scene)])


@router.post(
    "",
    response_model=SceneOut,
    status_code=202,
    responses={**REJECTED, **NEW_WORK_REFUSED},
    dependencies=[Depends(require_disk_space)],
    summary="Photos to novel views: reconstruction, NeRF, orbit video and held-out renders",
)
def create_scene(
    request: Request,
    response: Response,
    store: StoreDep,
    client: ClientDep,
    executor: ExecutorDep,
    settings: SettingsDep,
    images: Annotated[
        list[UploadFile] | None, File(description="The photographs (PNG/JPEG), all of one size, or one "
                                      "video (MP4/MOV, MKV/WebM, AVI) whose keyframes are used.")
    ] = None,
    photos_zip: Annotated[
        UploadFile | None,
        File(
            description="Instead of (or besides) `images`: a zip of the photos, optionally with its "
            "matching<i>.txt files and calibration.txt."
        ),
    ] = None,  # fmt: skip
    matches: Annotated[list[UploadFile] | None, File(description="Optional matching<i>.txt files.")] = None,
    calibration: Annotated[
        UploadFile | None, File(description="calibration.txt: the 3x3 K, row by row.")
    ] = None,
    K: Annotated[
        str | None, Form(max_length=1000, description="K instead of a file: 9 numbers row by row.")
    ] = None,
    features: Annotated[Literal["auto", "matches", "sift"], Form()] = "auto",
    ransac_threshold_px: Annotated[float | None, Form(gt=0, le=100)] = None,
    ba_max_iterations: Annotated[int | None, Form(ge=1, le=10000)] = None,
    model: Annotated[Literal["vanilla", "fast"], Form()] = "fast",
    steps: Annotated[int | None, Form(ge=1, le=10_000_000)] = None,
    minutes: Annotated[float | None, Form(gt=0, le=100_000)] = None,
    batch_rays: Annotated[int | None, Form(ge=1, le=1_000_000)] = None,
    device: Annotated[Literal["auto", "cpu", "cuda"] | None, Form()] = None,
    options: Annotated[
        str | None, Form(max_length=20_000, description="More NeRF TrainConfig fields as a JSON object.")
    ] = None,
    min_registered_images: Annotated[int, Form(ge=2, le=10_000)] = 3,
    orbit_frames: Annotated[int, Form(ge=1, le=720)] = 36,
    orbit_max_side: Annotated[int, Form(ge=8, le=4096)] = 200,
    held_out_max_side: Annotated[int, Form(ge=8, le=4096)] = 200,
    train_max_side: Annotated[
        int | None,
        Form(
            ge=8,
            le=16_384,
            description="Long side of the training photos (default: what the budget "
            "can train, chosen from a timed probe and recorded in the NeRF's config.json).",
        ),
    ] = None,  # fmt: skip
    views_share: Annotated[
        float,
        Form(ge=0, le=100, description="The views (video and held-out renders) take at most this share of "
             "the training time: fewer frames or smaller renders when they would take longer (0: as asked)."),
    ] = VIEWS_SHARE,  # fmt: skip
) -> SceneOut:
    inputs = SceneInputs(
        photos=ReconstructionInputs(
            images=input_files(images), matches=input_files(matches), calibration=input_file(calibration),
            K=K, features=features, ransac_threshold_px=ransac_threshold_px,
            ba_max_iterations=ba_max_iterations,
        ),
        train=TrainOptions(
            model=model, steps=steps, minutes=minutes, batch_rays=batch_rays, device=device,
            max_side=train_max_side, options=options,
        ),
        photos_zip=input_file(photos_zip),
        options={"min_registered_images": min_registered_images, "orbit_frames": orbit_frames,
                 "orbit_max_side": orbit_max_side, "held_out_max_side": held_out_max_side,
                 "views_share": views_share},
    )  # fmt: skip
    scene = create(store, executor, settings, client, inputs)
    out = _describe(scene, request)
    response.status_code = status.HTTP_202_ACCEPTED
    response.headers["Location"] = out.links["self"]
    return out


@router.get("", response_model=SceneList, summary="List scenes, newest first")
def list_scenes(
    request: Request,
    store: StoreDep,
    client: ClientDep,
    state: Annotated[JobState | None, Query(description="Only scenes in this state.")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> SceneList:
    owner = None if client.admin else client.name
    rows, total = store.list_scenes(state=state, owner=owner, limit=limit, offset=offset)
    return SceneList(items=[_describe(s, request) for s in rows], total=total, limit=limit, offset=offset)


@router.get(
    "/{scene_id}",
    response_model=SceneOut,
    responses=SCENE_NOT_FOUND,
    summary="A scene's stage, overall and per-stage progress, log and links to every artifact",
)
def get_scene(scene_id: SceneIdPath, request: Request) -> SceneOut:
    return _describe(_find(request, scene_id), request)


@router.post(
    "/{scene_id}/cancel",
    response_model=SceneOut,
    responses={**SCENE_NOT_FOUND, **CONFLICT},
    summary="Cancel a running scene (its running child jobs are cancelled)",
)
def cancel_scene(
    scene_id: SceneIdPath, request: Request, store: StoreDep, executor: ExecutorDep, settings: SettingsDep
) -> SceneOut:
    with scene_lock:
        cancel(store, executor, settings, _find(request, scene_id))
    return _describe(_find(request, scene_id), request)


@router.post(
    "/{scene_id}/retry",
    response_model=SceneOut,
    status_code=202,
    responses={**SCENE_NOT_FOUND, **CONFLICT, **NEW_WORK_REFUSED},
    dependencies=[Depends(require_disk_space)],
    summary="Run a failed or cancelled scene again from the stage it stopped at",
)
def retry_scene(
    scene_id: SceneIdPath,
    request: Request,
    response: Response,
    store: StoreDep,
    executor: ExecutorDep,
    settings: SettingsDep,
) -> SceneOut:
    with scene_lock:
        retry(store, executor, settings, _find(request, scene_id))
    return accepted(response, _describe(_find(request, scene_id), request))


@router.delete(
    "/{scene_id}",
    status_code=204,
    response_class=Response,
    responses=SCENE_NOT_FOUND,
    summary="Delete a scene, its child jobs and all their files (a running scene is cancelled first)",
)
def delete_scene(
    scene_id: SceneIdPath, request: Request, store: StoreDep, executor: ExecutorDep, settings: SettingsDep
) -> Response:
    with scene_lock:
        delete(store, executor, settings, _find(request, scene_id))
    return Response(status_code=204)


@router.get(
    "/{scene_id}/held-out/{name}",
    response_class=FileResponse,
    responses={**SCENE_NOT_FOUND, **file_response("image/png", description="The render of a held-out view.")},
    summary="The NeRF's render of one held-out view",
)
def get_held_out(scene_id: SceneIdPath, name: str, request: Request) -> FileResponse:
    scene = _find(request, scene_id)
    folder = output_dir(request.app.state.settings, scene.evaluation_job_id or "-")
    path = folder / Path(name).name
    if not scene.evaluation_job_id or Path(name).name != name or path.suffix != ".png" or not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id} has no held-out render {name!r}")
    return FileResponse(path, media_type="image/png")
