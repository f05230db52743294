"""/v1/reconstructions: upload an image set and its matches, then fetch poses, points and exports."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Response, UploadFile, status
from fastapi.responses import FileResponse

from service import webhooks
from service.db import JobKind, JobState, new_job_id
from service.deps import ClientDep, ExecutorDep, JobIdPath, SettingsDep, StoreDep, find_job
from service.models import ErrorOut, JobOut, ReconstructionOut
from service.openapi import file_response
from service.params import ReconstructionParams
from service.routes.jobs import NO_SPACE, NOT_FOUND, accepted, require_disk_space
from service.runner import input_dir, job_dir, output_dir
from service.uploads import (
    UploadRejected,
    inside,
    invalid,
    removed_on_failure,
    sanitize_filename,
    save_images,
    save_stream,
)
from service.validation import check_isolated
from service.video_uploads import is_video_upload, save_video

router = APIRouter(prefix="/v1/reconstructions", tags=["reconstructions"])
MATCH_NAME = re.compile(r"^matching(\d+)\.txt$")
CALIBRATION_NAME = "calibration.txt"
REPORT_FIELDS_SHOWN_APART = ("intrinsics", "cameras", "unregistered")
NOT_READY = {409: {"model": ErrorOut, "description": "The job has not succeeded (yet)."}}
REJECTED = {
    413: {"model": ErrorOut, "description": "A limit was exceeded (named in the message)."},
    422: {"description": "Bad input; the message names the field and file."},
}


def _parse_k(text: str, source: str) -> Any:
    from estimation.errors import InputError
    from estimation.io.images import parse_calibration

    try:
        return parse_calibration(text, source)
    except InputError as error:
        raise invalid(f"calibration: {error}") from None


def _k_from_numbers(numbers: str) -> str:
    """'fx 0 cx 0 fy cy 0 0 1' (commas, semicolons or spaces) -> calibration.txt text, 3 rows."""
    tokens = [t for t in re.split(r"[\s,;\[\]]+", numbers) if t]
    if len(tokens) != 9:
        raise invalid(f"K: expected 9 numbers (the 3x3 matrix row by row), found {len(tokens)}")
    return "\n".join(" ".join(tokens[row * 3 : row * 3 + 3]) for row in range(3)) + "\n"


def _store_calibration(folder: Path, calibration: UploadFile | None, K: str | None) -> None:
    """calibration.txt from the file or the 9 numbers of K, checked; none when neither is given."""
    if calibration is not None and K:
        raise invalid("calibration: give either the calibration file or K, not both")
    if calibration is not None:
        text = calibration.file.read(64 * 1024).decode("utf-8", errors="replace")
        source = sanitize_filename(calibration.filename or CALIBRATION_NAME, "calibration")
    elif K:
        text, source = _k_from_numbers(K), "K"
    else:   # no calibration: the reconstruction takes the focal length from EXIF or a prior, and refines it
        return
    _parse_k(text, source)
    inside(folder, CALIBRATION_NAME).write_text(text)


def _store_inputs(
    folder: Path,
    settings: Any,
    images: list[UploadFile],
    matches: list[UploadFile],
    calibration: UploadFile | None,
    K: str | None,
    features: str,
) -> None:
    """Saves and checks everything the reconstruction reads; UploadRejected on the first problem."""
    if any(is_video_upload(upload) for upload in images):
        if matches:
            raise invalid("matches: match files go with photos, not with a video")
        video = save_video(images, folder, settings)
        check_isolated("input_video", {"field": "images", "path": str(folder / video.name),
                                       "name": video.name}, settings)
        _store_calibration(folder, calibration, K)
        return
    saved = save_images(((f.filename, f.file) for f in images), folder, settings)
    if len(saved) < 2:
        raise invalid(f"images: {len(saved)} image(s) uploaded, a reconstruction needs at least 2")
    first = saved[0]
    for image in saved[1:]:
        if (image.width, image.height) != (first.width, first.height):
            raise invalid(
                f"images: {image.name} is {image.width}x{image.height} but {first.name} is "
                f"{first.width}x{first.height}; all images must have the same size"
            )
    _store_calibration(folder, calibration, K)

    if features == "matches" and not matches:
        raise invalid("matches: features='matches' needs the matching<i>.txt files")
    match_files = []
    for upload in matches:
        name = sanitize_filename(upload.filename, "matches")
        found = MATCH_NAME.match(name)
        if not found:
            raise invalid(
                f"matches: file {name!r} must be named matching<i>.txt, <i> an image's numeric name"
            )
        target = inside(folder, name)
        if target.exists():
            raise invalid(f"matches: two files are named {name!r}")
        save_stream(upload.file, target)
        match_files.append((name, int(found.group(1))))
    # Decoding the images and parsing the match files take memory in proportion to the upload: a worker.
    check_isolated(
        "reconstruction_inputs",
        {
            "field": "images",
            "folder": str(folder),
            "images": [image.name for image in saved],
            "matches": match_files,
            "image_ids": [int(Path(image.name).stem) for image in saved if Path(image.name).stem.isdigit()],
            "width": first.width,
            "height": first.height,
        },
        settings,
    )


@router.post(
    "",
    response_model=JobOut,
    status_code=202,
    responses={**REJECTED, **NO_SPACE},
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
    from estimation.config import ReconstructionConfig

    webhook_url = webhooks.check_url(webhook_url, settings)
    job_id = new_job_id()
    folder = input_dir(settings, job_id)
    with removed_on_failure(job_dir(settings, job_id)):
        folder.mkdir(parents=True)
        _store_inputs(folder, settings, images, matches or [], calibration, K, features)
        config = ReconstructionConfig(features=features).model_dump(mode="json")
        if ransac_threshold_px is not None:
            config["ransac"]["threshold_px"] = ransac_threshold_px
        if ba_max_iterations is not None:
            config["bundle_adjustment"]["max_iterations"] = ba_max_iterations
        job = store.create(
            JobKind.reconstruction,
            ReconstructionParams(config=config),
            job_id=job_id,
            webhook_url=webhook_url,
            owner=client.name,
        )
    executor.submit(job_id)
    return accepted(response, JobOut.from_job(job))


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
    report_path = output_dir(settings, job_id) / "report.json"
    if job.state != JobState.succeeded or not report_path.is_file():
        return out
    report = json.loads(report_path.read_text())
    base = f"/v1/reconstructions/{job_id}"
    files = {name: f"{base}/{name}" for name in ("points.ply", "colmap.zip", "transforms.json")}
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
        _succeeded_output(store, settings, job_id) / "points.ply", "application/octet-stream", "points.ply"
    )


@router.get(
    "/{job_id}/transforms.json",
    responses={**NOT_FOUND, **NOT_READY},
    summary="Cameras in nerfstudio's transforms.json format",
)
def get_transforms(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    return _file(_succeeded_output(store, settings, job_id) / "transforms.json", "application/json")


@router.get(
    "/{job_id}/colmap.zip",
    response_class=FileResponse,
    responses={**NOT_FOUND, **NOT_READY, **file_response("application/zip", description="Zip archive.")},
    summary="The model in COLMAP text format (cameras.txt, images.txt, points3D.txt), zipped",
)
def get_colmap(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    out = _succeeded_output(store, settings, job_id)
    archive = out / "colmap.zip"
    if not archive.is_file():
        sparse = out / "sparse"
        if not sparse.is_dir():
            raise HTTPException(status.HTTP_404_NOT_FOUND, "this reconstruction wrote no COLMAP model")
        partial = archive.with_suffix(".zip.partial")
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as zf:
            for path in sorted(sparse.iterdir()):
                if path.is_file():
                    zf.write(path, f"sparse/{path.name}")
        partial.replace(archive)
    return FileResponse(archive, media_type="application/zip", filename="colmap.zip")


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
