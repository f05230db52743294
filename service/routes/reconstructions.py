"""/v1/reconstructions: upload an image set and its matches, then fetch poses, points and exports."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Response, UploadFile, status
from fastapi.responses import FileResponse

from estimation.artefacts import PLY_NAME, SPARSE_DIR, TRANSFORMS_NAME
from service.actions.jobs import find_job
from service.actions.reconstructions import ReconstructionInputs
from service.actions.reconstructions import create_reconstruction as create
from service.deps import ClientDep, ExecutorDep, JobIdPath, SettingsDep, StoreDep, require_disk_space
from service.kinds import JobKind, JobState
from service.layout import COLMAP_ARCHIVE, RECONSTRUCTION_EXPORTS, RECONSTRUCTION_REPORT, output_dir
from service.openapi import file_response
from service.routes.common import NEW_WORK_REFUSED, NOT_FOUND, REJECTED, accepted, input_file, input_files
from service.schemas import ErrorOut, JobOut, ReconstructionOut
from service.uploads import UploadRejected, inside, sanitize_filename

router = APIRouter(prefix="/v1/reconstructions", tags=["reconstructions"])
REPORT_FIELDS_SHOWN_APART = ("intrinsics", "cameras", "unregistered")
NOT_READY = {409: {"model": ErrorOut, "description": "The job has not succeeded (yet)."}}


@router.post(
    "",
    response_model=JobOut,
    status_code=202,
    responses={**REJECTED, **NEW_WORK_REFUSED},
    dependencies=[Depends(require_disk_space)],
    summary="Upload images (+ match files, calibration) and start a reconstruction",
)
def create_reconstruction(
    response: Response,
    store: StoreDep,
    client: ClientDep,
    executor: ExecutorDep,
    settings: SettingsDep,
    images: Annotated[list[UploadFile], File(description="The photographs (PNG/JPEG), all of one size, or "
                                             "one video (MP4/MOV, MKV/WebM, AVI) whose keyframes are used.")],
    matches: Annotated[
        list[UploadFile] | None,
        File(description="Optional matching<i>.txt files (image ids are the images' numeric names)."),
    ] = None,
    calibration: Annotated[
        UploadFile | None, File(description="calibration.txt: the 3x3 K, row by row. Without it (or K) the "
                                "camera is calibrated from the photos' EXIF or a prior, and refined.")
    ] = None,
    K: Annotated[
        str | None,
        Form(
            description="K instead of a file: 9 numbers row by row.",
            max_length=1000,
            examples=["719.5 0 400 0 719.5 300 0 0 1"],
        ),
    ] = None,
    features: Annotated[
        Literal["auto", "matches", "sift"], Form(description="auto: the match files when given, else SIFT.")
    ] = "auto",
    ransac_threshold_px: Annotated[
        float | None, Form(gt=0, le=100, examples=[1.0], description="RANSAC inlier threshold, pixels.")
    ] = None,
    ba_max_iterations: Annotated[
        int | None, Form(ge=1, le=10000, examples=[100], description="Bundle adjustment iterations.")
    ] = None,
    webhook_url: Annotated[
        str | None,
        Form(pattern=r"^https?://\S+$", max_length=2000, description="Called with the job when it ends."),
    ] = None,
) -> JobOut:
    inputs = ReconstructionInputs(
        images=input_files(images), matches=input_files(matches),
        calibration=input_file(calibration), K=K, features=features,
        ransac_threshold_px=ransac_threshold_px, ba_max_iterations=ba_max_iterations, webhook_url=webhook_url,
    )  # fmt: skip
    return accepted(response, JobOut.from_job(create(store, executor, settings, client, inputs)))


def _succeeded_output(store: Any, settings: Any, job_id: str) -> Path:
    job = find_job(store, job_id, JobKind.reconstruction)
    if job.state != JobState.succeeded:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"reconstruction {job_id} is {job.state}; its results exist once it succeeded",
        )
    return output_dir(settings, job_id)


@router.get(
    "/{job_id}",
    response_model=ReconstructionOut,
    responses=NOT_FOUND,
    summary="Intrinsics, camera poses, unregistered images and statistics",
)
def get_reconstruction(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> ReconstructionOut:
    job = find_job(store, job_id, JobKind.reconstruction)
    out = ReconstructionOut(job=JobOut.from_job(job))
    report_path = output_dir(settings, job_id) / RECONSTRUCTION_REPORT
    if job.state != JobState.succeeded or not report_path.is_file():
        return out
    report = json.loads(report_path.read_text())
    base = f"/v1/reconstructions/{job_id}"
    files = {name: f"{base}/{name}" for name in RECONSTRUCTION_EXPORTS}
    figures = output_dir(settings, job_id) / "figures"
    if figures.is_dir():
        files.update({f"figures/{p.name}": f"{base}/figures/{p.name}" for p in sorted(figures.glob("*.png"))})
    return ReconstructionOut(
        job=out.job,
        intrinsics=report.get("intrinsics"),
        cameras=report.get("cameras", []),
        unregistered=report.get("unregistered", []),
        statistics={k: v for k, v in report.items() if k not in REPORT_FIELDS_SHOWN_APART},
        files=files,
    )


def _file(path: Path, media_type: str, filename: str | None = None) -> FileResponse:
    if not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"{path.name} was not written by this reconstruction")
    return FileResponse(path, media_type=media_type, filename=filename)


@router.get(
    "/{job_id}/points.ply",
    response_class=FileResponse,
    responses={
        **NOT_FOUND,
        **NOT_READY,
        **file_response("application/octet-stream", description="PLY file."),
    },
    summary="The sparse point cloud (PLY)",
)
def get_points(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    return _file(
        _succeeded_output(store, settings, job_id) / PLY_NAME, "application/octet-stream", PLY_NAME
    )


@router.get(
    "/{job_id}/transforms.json",
    responses={**NOT_FOUND, **NOT_READY},
    summary="Cameras in nerfstudio's transforms.json format",
)
def get_transforms(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    return _file(_succeeded_output(store, settings, job_id) / TRANSFORMS_NAME, "application/json")


@router.get(
    "/{job_id}/colmap.zip",
    response_class=FileResponse,
    responses={**NOT_FOUND, **NOT_READY, **file_response("application/zip", description="Zip archive.")},
    summary="The model in COLMAP text format (cameras.txt, images.txt, points3D.txt), zipped",
)
def get_colmap(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    out = _succeeded_output(store, settings, job_id)
    archive = out / COLMAP_ARCHIVE
    if not archive.is_file():
        sparse = out / SPARSE_DIR
        if not sparse.is_dir():
            raise HTTPException(status.HTTP_404_NOT_FOUND, "this reconstruction wrote no COLMAP model")
        partial = archive.with_suffix(".zip.partial")
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as zf:
            for path in sorted(sparse.iterdir()):
                if path.is_file():
                    zf.write(path, f"{SPARSE_DIR}/{path.name}")
        partial.replace(archive)
    return FileResponse(archive, media_type="application/zip", filename=COLMAP_ARCHIVE)


@router.get(
    "/{job_id}/figures/{name}",
    response_class=FileResponse,
    responses={**NOT_FOUND, **NOT_READY, **file_response("image/png", description="PNG image.")},
    summary="A figure (PNG) of the reconstruction",
)
def get_figure(job_id: JobIdPath, name: str, store: StoreDep, settings: SettingsDep) -> FileResponse:
    figures = _succeeded_output(store, settings, job_id) / "figures"
    try:
        path = inside(figures, sanitize_filename(name, "name"))
    except UploadRejected:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no figure named {name!r}") from None
    if path.name != name or not path.is_file():
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no figure named {name!r}")
    return FileResponse(path, media_type="image/png")
