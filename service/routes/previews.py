"""Pictures of a NeRF run for people watching it train: the latest validation render."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, status
from fastapi.responses import FileResponse

from service.actions.jobs import find_job
from service.deps import JobIdPath, SettingsDep, StoreDep
from service.kinds import JobKind
from service.layout import output_dir
from service.openapi import file_response
from service.routes.common import NOT_FOUND
from service.schemas import ErrorOut

router = APIRouter(prefix="/v1/nerf", tags=["nerf"])
VALIDATION_FOLDER = "val"


@router.get(
    "/{job_id}/validation",
    response_class=FileResponse,
    responses={
        **NOT_FOUND,
        409: {"model": ErrorOut, "description": "No validation render yet."},
        **file_response("image/png", description="Ground truth | render | depth, first validation view."),
    },
    summary="The latest validation render (ground truth | render | depth)",
)
def get_validation(job_id: JobIdPath, store: StoreDep, settings: SettingsDep) -> FileResponse:
    find_job(store, job_id, JobKind.nerf)
    renders = sorted((output_dir(settings, job_id) / VALIDATION_FOLDER).glob("step_*.png"))
    if not renders:
        raise HTTPException(status.HTTP_409_CONFLICT, f"NeRF job {job_id} has no validation render yet")
    return FileResponse(renders[-1], media_type="image/png")
