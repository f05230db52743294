"""Request and response models of the REST API (pydantic), with the examples shown in the OpenAPI schema."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.kinds import JobKind, JobState
from service.params import VideoParams
from service.store.tables import Job

JOB_ID_EXAMPLE = "3f2b8c1d9e7a4b6c8d0e1f2a3b4c5d6e"


class ErrorOut(BaseModel):
    detail: str = Field(..., examples=["job 3f2b8c1d9e7a4b6c8d0e1f2a3b4c5d6e not found"])


class JobOut(BaseModel):
    """A job's resource: what it is, where it stands and how it ended."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": JOB_ID_EXAMPLE,
                    "kind": "reconstruction",
                    "state": "running",
                    "stage": "bundle adjustment",
                    "progress": 0.62,
                    "created_at": "2026-11-21T07:00:00Z",
                    "started_at": "2026-11-21T07:00:01Z",
                    "finished_at": None,
                    "error": None,
                    "attempt": 1,
                    "source_job_id": None,
                    "retry_of": None,
                    "webhook_url": None,
                    "worker": "local",
                    "pinned": False,
                    "result": None,
                    "links": {
                        "self": f"/v1/jobs/{JOB_ID_EXAMPLE}",
                        "logs": f"/v1/jobs/{JOB_ID_EXAMPLE}/logs",
                        "result": f"/v1/reconstructions/{JOB_ID_EXAMPLE}",
                    },
                }
            ]
        }
    )

    id: str
    kind: JobKind
    state: JobState
    stage: str | None = Field(None, description="Name of the step running now.")
    progress: float = Field(..., ge=0, le=1, description="Overall fraction done, 0..1.")
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: str | None = Field(None, description="Why the job failed, naming the file, line or field.")
    attempt: int = Field(..., description="How many times the job was started (restarts included).")
    source_job_id: str | None = Field(
        None, description="The reconstruction a NeRF job trains on, or the NeRF job a video renders."
    )
    retry_of: str | None = Field(None, description="The job this one retries.")
    webhook_url: str | None = None
    worker: str | None = Field(None, description="The process running the job.")
    pinned: bool = Field(
        False, description="Kept past SFMNERF_JOB_RETENTION_MINUTES (PUT/DELETE /v1/jobs/{id}/pin)."
    )
    result: dict[str, Any] | None = Field(None, description="A short summary of the outcome.")
    links: dict[str, str]

    @classmethod
    def from_job(cls, job: Job) -> JobOut:
        links = {"self": f"/v1/jobs/{job.id}", "logs": f"/v1/jobs/{job.id}/logs"}
        if job.kind == JobKind.reconstruction:
            links["result"] = f"/v1/reconstructions/{job.id}"
        elif job.kind == JobKind.nerf:
            links["result"] = f"/v1/nerf/{job.id}"
        elif job.kind == JobKind.video and job.source_job_id:
            links["result"] = f"/v1/nerf/{job.source_job_id}/video"
        return cls(
            id=job.id,
            kind=JobKind(job.kind),
            state=JobState(job.state),
            stage=job.stage,
            progress=job.progress,
            created_at=job.created_at,
            started_at=job.started_at,
            finished_at=job.finished_at,
            error=job.error,
            attempt=job.attempt,
            source_job_id=job.source_job_id,
            retry_of=job.retry_of,
            webhook_url=job.webhook_url,
            worker=job.worker,
            pinned=bool(job.pinned),
            result=job.result,
            links=links,
        )


class JobList(BaseModel):
    items: list[JobOut]
    total: int = Field(..., examples=[42], description="Jobs matching the filters.")
    limit: int = Field(..., examples=[50])
    offset: int = Field(..., examples=[0])


class LogsOut(BaseModel):
    job_id: str = Field(..., examples=[JOB_ID_EXAMPLE])
    offset: int = Field(..., examples=[0], description="Index of the first line returned.")
    next_offset: int = Field(..., examples=[3], description="Pass this as `offset` to get the lines after.")
    lines: list[str] = Field(..., examples=[["stage: tracks (0%)", "stage: initial pair (10%)"]])


class Intrinsics(BaseModel):
    K: list[list[float]] = Field(
        ..., examples=[[[1000.0, 0.0, 400.0], [0.0, 1000.0, 300.0], [0.0, 0.0, 1.0]]]
    )
    width: int = Field(..., examples=[800])
    height: int = Field(..., examples=[600])


class CameraOut(BaseModel):
    """A registered image's pose: world-to-camera x_cam = R X + t (OpenCV axes); centre C = -R^T t."""

    image: str = Field(..., examples=["1.png"])
    R: list[list[float]] = Field(..., examples=[[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    t: list[float] = Field(..., examples=[[0.0, 0.0, 0.0]])
    C: list[float] = Field(..., examples=[[0.0, 0.0, 0.0]])


class UnregisteredOut(BaseModel):
    image: str = Field(..., examples=["5.png"])
    reason: str = Field(..., examples=["only 3 2D-3D correspondences (need 6)"])


class ReconstructionOut(BaseModel):
    """A reconstruction job and, once it succeeded, its model (from report.json)."""

    job: JobOut
    intrinsics: Intrinsics | None = None
    cameras: list[CameraOut] = Field(default_factory=list)
    unregistered: list[UnregisteredOut] = Field(default_factory=list)
    statistics: dict[str, Any] = Field(
        default_factory=dict,
        description="The rest of report.json: reprojection errors, inlier counts, timings.",
        examples=[{"num_points": 2810, "final_rms_px": 0.61}],
    )
    files: dict[str, str] = Field(
        default_factory=dict,
        examples=[{"points.ply": f"/v1/reconstructions/{JOB_ID_EXAMPLE}/points.ply"}],
        description="Downloads: points.ply, colmap.zip, transforms.json and figures/{name}.",
    )


class MetricPoint(BaseModel):
    model_config = ConfigDict(extra="allow")

    step: int = Field(..., examples=[100])
    loss: float | None = Field(None, examples=[0.012])
    psnr: float | None = Field(None, examples=[19.4])


class CheckpointOut(BaseModel):
    step: int = Field(..., examples=[1000])
    is_latest: bool
    is_best: bool
    val_psnr: float | None = Field(None, examples=[24.1])
    size_bytes: int = Field(..., examples=[2_400_000])
    url: str = Field(..., examples=[f"/v1/nerf/{JOB_ID_EXAMPLE}/checkpoints/1000"])


class NerfOut(BaseModel):
    """A NeRF training job with its metrics so far (from metrics.jsonl)."""

    job: JobOut
    config: dict[str, Any] | None = Field(None, description="The training configuration (config.json).")
    metrics: list[MetricPoint] = Field(default_factory=list)
    latest_step: int | None = Field(None, examples=[1000])
    links: dict[str, str] = Field(default_factory=dict)


MAX_COORDINATE = 1e6
"""Largest |value| of a render request's eye, look_at, up and c2w entries: poses live in the scene's own
frame (a radius of a few units); far beyond it the look-at maths overflows (norms of ~1e156)."""
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
Vector3 = list[Coordinate]


class RenderRequest(BaseModel):
    """A camera to render from: a 4x4 camera-to-world matrix (OpenGL axes), or eye + look-at + up, or none
    for the default view (the registered photo nearest the middle of the camera path)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "eye": [0.0, -4.0, 2.0],
                    "look_at": [0.0, 0.0, 0.0],
                    "up": [0.0, 0.0, 1.0],
                    "width": 200,
                    "height": 200,
                    "fov_x_deg": 40.0,
                },
                {
                    "c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
                    "width": 100,
                    "height": 100,
                    "fx": 138.9,
                },
                {"width": 200, "height": 150},
            ]
        }
    )

    c2w: list[list[Coordinate]] | None = Field(None, description="4x4 camera-to-world, OpenGL camera axes.")
    eye: Vector3 | None = Field(None, min_length=3, max_length=3)
    look_at: Vector3 | None = Field(None, min_length=3, max_length=3)
    up: Vector3 | None = Field(None, min_length=3, max_length=3)
    width: int = Field(..., ge=1, le=4096)
    height: int = Field(..., ge=1, le=4096)
    fx: float | None = Field(None, gt=0, description="Focal length in pixels (default: the dataset's).")
    fov_x_deg: float | None = Field(None, gt=0, lt=180, description="Horizontal field of view instead of fx.")
    checkpoint: Literal["latest", "best"] | int = Field("latest", description="latest, best or a step.")
    frame: Literal["auto", "capture", "data"] = Field(
        "auto",
        description="How c2w / eye / look_at / up are read. capture: relative to the photos (origin at "
        "what they look at, z up, the default photo's camera at (0, -4, h)), so eye [0,-4,1] looking at "
        "the origin sees the scene; data: the dataset's own frame (free mode); auto: capture for photo "
        "scenes, data for Blender and .npz datasets.",
    )

    allow_empty_view: bool = Field(
        False,
        description="Return the image even when it sees nothing of the scene (under 1 % of its pixels "
        "opaque), e.g. live views of a field still training; otherwise such a view is a 422 saying so.",
    )

    @model_validator(mode="after")
    def _one_camera(self) -> RenderRequest:
        look_at_given = [v is not None for v in (self.eye, self.look_at)]
        if self.c2w is not None and any(look_at_given):
            raise ValueError("give either c2w or eye + look_at (+ up), not both")
        if any(look_at_given) and not all(look_at_given):
            raise ValueError("eye and look_at go together (or leave the camera out for the default view)")
        if self.fx is not None and self.fov_x_deg is not None:
            raise ValueError("give either fx or fov_x_deg, not both")
        if self.c2w is not None:
            matrix = np.asarray(self.c2w, dtype=float) if _is_rectangular(self.c2w) else None
            if matrix is None or matrix.shape != (4, 4) or not np.isfinite(matrix).all():
                raise ValueError("c2w must be a 4x4 matrix of finite numbers")
        else:
            self.camera_to_world()  # raises ValueError on a degenerate eye/look_at/up
        return self

    def camera_to_world(self) -> np.ndarray | None:
        """The 4x4 camera-to-world matrix (OpenGL: x right, y up, looking down -z); None: the default view."""
        if self.c2w is not None:
            return np.asarray(self.c2w, dtype=float)
        if self.eye is None:
            return None
        return look_at_c2w(
            np.asarray(self.eye, float),
            np.asarray(self.look_at, float),
            np.asarray(self.up if self.up is not None else [0.0, 0.0, 1.0], float),
        )


def _is_rectangular(rows: list[list[float]]) -> bool:
    return len({len(row) for row in rows}) == 1


def look_at_c2w(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world whose -z axis points from eye to target: [right, up', -forward, eye]."""
    if not (np.isfinite(eye).all() and np.isfinite(target).all() and np.isfinite(up).all()):
        raise ValueError("eye, look_at and up must be finite numbers")
    forward = target - eye
    if np.linalg.norm(forward) < 1e-9:
        raise ValueError("eye and look_at must differ")
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("up must not be parallel to the viewing direction")
    right = right / np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


class VideoRequest(VideoParams):
    """A video of the latest checkpoint (the video job's parameters)."""


class CameraPathOut(BaseModel):
    """How the photos were taken and the camera path through them; poses are 4x4 camera-to-world (OpenGL
    axes) in the dataset's own frame (send them back as c2w with frame "data")."""

    kind: Literal["ring", "arc", "walk"] = Field(..., description="ring: closed 360 degrees; arc: part of a "
        "circle round what the cameras look at; walk: cameras that do not look at one point.")  # fmt: skip
    span_deg: float = Field(..., examples=[75.0], description="Angle the cameras cover round their target.")
    closed: bool = Field(..., description="The path goes round (a ring) or there and back (arc, walk).")
    default_view: list[list[float]] = Field(..., description="The default novel view: a photo's camera.")
    cameras: list[list[list[float]]] = Field(..., description="The registered cameras, in path order.")
    path: list[list[list[float]]] = Field(..., description="num_frames poses of the default video path.")


class HealthOut(BaseModel):
    status: str = Field(..., examples=["ok"])


class ReadyOut(BaseModel):
    status: str = Field(..., examples=["ready"])
    database: str = Field(..., examples=["ok"])
    queue: str = Field(..., examples=["ok"])


class InfoOut(BaseModel):
    version: str = Field(..., examples=["0.1.0"])
    executor: Literal["local", "celery"]
    device: str = Field(..., examples=["cpu"], description="Where NeRF jobs run by default (torch).")
    queue_length: int = Field(..., examples=[2], description="Jobs waiting to start.")
    running: int = Field(..., examples=[1])
    concurrency: int = Field(..., examples=[1])
    limits: dict[str, int | float] = Field(..., examples=[{"max_images": 500, "max_upload_bytes": 536870912}])
