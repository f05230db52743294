"""/v1/scenes: photos in, novel views out; one resource over a reconstruction, a NeRF and its renders."""

from __future__ import annotations

import json
import tempfile
from contextlib import ExitStack
from datetime import datetime
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
from fastapi import Path as PathParam
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from neural.budget import expected_seconds
from service.db import JobState, Scene, new_job_id
from service.deps import ClientDep, ExecutorDep, SettingsDep, StoreDep
from service.models import ErrorOut, JobOut
from service.openapi import file_response
from service.routes.jobs import MAX_PAGE, NO_SPACE, accepted, require_disk_space
from service.routes.nerf import _train_config
from service.routes.reconstructions import REJECTED, create_reconstruction
from service.runner import EVALUATION_FILE, output_dir
from service.scenes import (
    DONE,
    STAGE_WEIGHTS,
    STAGES,
    SceneOptions,
    SceneRunner,
    scene_lock,
    scene_owner,
    stage_jobs,
)
from service.uploads import UploadRejected, extract_zip, sanitize_filename, save_stream

SCENE_NOT_FOUND = {404: {"model": ErrorOut, "description": "No scene with this id."}}
CONFLICT = {409: {"model": ErrorOut, "description": "Not possible in the scene's state."}}
ZIP_PHOTO_SUFFIXES = {".png", ".jpg", ".jpeg"}
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
        links.update({name: f"{base}/{name}" for name in ("points.ply", "colmap.zip", "transforms.json")})
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


def _runner(request: Request) -> SceneRunner:
    state = request.app.state
    return SceneRunner(state.store, state.executor, state.settings)


def _zip_photos(archive: UploadFile, folder: Path, settings: Any) -> dict[str, list[Path]]:
    """The photos, match files and calibration of an uploaded zip, extracted (safely) into folder."""
    target = folder / "photos.zip"
    save_stream(archive.file, target)
    extract_zip(target, folder / "photos", settings, field="photos_zip")
    files = sorted(p for p in (folder / "photos").rglob("*") if p.is_file() and not p.name.startswith("."))
    found: dict[str, list[Path]] = {
        "images": [p for p in files if p.suffix.lower() in ZIP_PHOTO_SUFFIXES],
        "matches": [p for p in files if p.name.startswith("matching") and p.suffix == ".txt"],
        "calibration": [p for p in files if p.name == "calibration.txt"],
    }
    if not found["images"]:
        raise UploadRejected(422, "photos_zip: the zip holds no PNG or JPEG photos")
    return found


@router.post(
    "",
    response_model=SceneOut,
    status_code=202,
    responses={**REJECTED, **NO_SPACE},
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
        list[UploadFile] | None, File(description="The photographs (PNG/JPEG), all of one size.")
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
) -> SceneOut:
    try:
        train_config = _train_config(
            options,
            {
                "model": model,
                "steps": steps,
                "minutes": minutes,
                "batch_rays": batch_rays,
                "device": device,
                "max_side": train_max_side,
            },  # fmt: skip
        )
    except UploadRejected as rejected:
        raise HTTPException(rejected.status_code, rejected.detail) from None
    scene_options = SceneOptions(
        train_config=train_config,
        min_registered_images=min_registered_images,
        orbit_frames=orbit_frames,
        orbit_max_side=orbit_max_side,
        held_out_max_side=held_out_max_side,
    )
    images, matches = list(images or []), list(matches or [])
    with ExitStack() as stack:
        if photos_zip is not None:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(dir=settings.data_dir)))
            try:
                found = _zip_photos(photos_zip, folder, settings)
            except UploadRejected as rejected:
                raise HTTPException(rejected.status_code, rejected.detail) from None

            def upload(path: Path) -> UploadFile:
                return UploadFile(
                    stack.enter_context(open(path, "rb")), filename=sanitize_filename(path.name, "photos_zip")
                )

            images += [upload(p) for p in found["images"]]
            matches += [upload(p) for p in found["matches"]]
            if calibration is None and K is None and found["calibration"]:
                calibration = upload(found["calibration"][0])
        if not images:
            raise HTTPException(422, "images: upload the photos as `images` or as a `photos_zip`")
        expected = expected_seconds(train_config.get("minutes"), len(images), scene_options.views_share)
        scene_options = scene_options.model_copy(update={"expected_seconds": expected})
        reconstruction = create_reconstruction(
            Response(), store, client, executor, settings, images=images, matches=matches,
            calibration=calibration, K=K, features=features, ransac_threshold_px=ransac_threshold_px,
            ba_max_iterations=ba_max_iterations, webhook_url=None,
        )  # fmt: skip
    scene = store.create_scene(
        Scene(
            id=new_job_id(),
            state=JobState.running,
            stage="reconstruction",
            params=scene_options.model_dump(mode="json"),
            reconstruction_job_id=reconstruction.id,
            log=[],
        )
    )
    store.update_scene(scene.id, log=f"reconstruction job {reconstruction.id} started")
    out = _describe(store.get_scene(scene.id), request)
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
def cancel_scene(scene_id: SceneIdPath, request: Request) -> SceneOut:
    with scene_lock:
        scene = _find(request, scene_id)
        if scene.state != JobState.running:
            raise HTTPException(status.HTTP_409_CONFLICT, f"scene {scene_id} is already {scene.state}")
        _runner(request).cancel(scene)
    return _describe(_find(request, scene_id), request)


@router.post(
    "/{scene_id}/retry",
    response_model=SceneOut,
    status_code=202,
    responses={**SCENE_NOT_FOUND, **CONFLICT, **NO_SPACE},
    dependencies=[Depends(require_disk_space)],
    summary="Run a failed or cancelled scene again from the stage it stopped at",
)
def retry_scene(scene_id: SceneIdPath, request: Request, response: Response) -> SceneOut:
    with scene_lock:
        scene = _find(request, scene_id)
        if scene.state not in (JobState.failed, JobState.cancelled):
            raise HTTPException(
                status.HTTP_409_CONFLICT,
                f"only failed or cancelled scenes can be retried; {scene_id} is {scene.state}",
            )
        try:
            _runner(request).retry(scene)
        except ValueError as error:
            raise HTTPException(status.HTTP_409_CONFLICT, str(error)) from None
    return accepted(response, _describe(_find(request, scene_id), request))


@router.delete(
    "/{scene_id}",
    status_code=204,
    response_class=Response,
    responses=SCENE_NOT_FOUND,
    summary="Delete a scene, its child jobs and all their files (a running scene is cancelled first)",
)
def delete_scene(scene_id: SceneIdPath, request: Request) -> Response:
    with scene_lock:
        _runner(request).delete(_find(request, scene_id))
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
