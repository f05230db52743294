"""Creating NeRF, orbit video and held-out evaluation jobs, and the checks they share with scenes:
training options (device included), render sizes and the video budget, checkpoints."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import ValidationError

from neural.config import ModelName
from service import strict_json, webhooks
from service.actions.jobs import find_job
from service.actions.reconstructions import InputFile
from service.auth import Client
from service.errors import ServiceError, conflict
from service.executor import Executor
from service.kinds import JobKind, JobState
from service.layout import INPUT_DIR, job_dir, output_dir
from service.params import EvaluationParams, NerfParams, VideoParams
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job, SceneChild, new_job_id
from service.uploads import (
    extract_zip,
    find_dataset_root,
    invalid,
    removed_on_failure,
    sanitize_filename,
    save_stream,
)
from service.validation import check_isolated, check_npz_headers

DATASET_DIR = f"{INPUT_DIR}/dataset"
DATASET_NPZ = f"{INPUT_DIR}/dataset.npz"
DATASET_ZIP = f"{INPUT_DIR}/upload.zip"


@dataclass
class TrainOptions:
    """A NeRF's training options as a client gives them: named fields over a JSON object of the rest."""

    model: ModelName = "fast"
    steps: int | None = None
    minutes: float | None = None
    batch_rays: int | None = None
    device: Literal["auto", "cpu", "cuda"] | None = None
    max_side: int | None = None
    """Long side of the training photos (None: what the budget can train, for photos)."""
    options: str | None = None
    """More neural.TrainConfig fields as a JSON object."""

    def train_config(self, settings: ServiceSettings) -> dict[str, Any]:
        """The TrainConfig fields as JSON, validated by neural.TrainConfig and against this machine's
        devices; 422 naming the field otherwise. The one check of every NeRF's options (jobs, scenes)."""
        from neural import TrainConfig

        try:
            extra = strict_json.loads(self.options, "options") if self.options else {}
        except strict_json.JsonRefused as refused:
            raise invalid(str(refused)) from None
        if not isinstance(extra, dict):
            raise invalid("options: expected a JSON object of training settings")
        named = {"model": self.model, "steps": self.steps, "minutes": self.minutes,
                 "batch_rays": self.batch_rays, "device": self.device, "max_side": self.max_side}  # fmt: skip
        try:
            given = {k: v for k, v in named.items() if v is not None}
            config = TrainConfig.model_validate({**extra, **given})
        except ValidationError as error:
            problems = "; ".join(
                f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in error.errors()
            )
            raise invalid(f"training options: {problems}") from None
        _check_device(config.device, settings)
        return config.model_dump(mode="json")


def _check_device(device: str, settings: ServiceSettings) -> None:
    """device=cuda needs a CUDA GPU on this machine (local jobs run here; Celery workers are not known)."""
    if device != "cuda" or settings.executor != "local":
        return
    import torch

    if not torch.cuda.is_available():
        raise invalid("device: 'cuda' was asked for but this machine has no CUDA GPU; use 'cpu' or 'auto'")


@dataclass
class NerfInputs:
    """A NeRF job: its training data (an uploaded dataset or a finished reconstruction) and options."""

    train: TrainOptions
    dataset: InputFile | None = None
    reconstruction_id: str | None = None
    webhook_url: str | None = None


def _save_dataset(upload: InputFile, job_id: str, settings: ServiceSettings) -> str:
    """Stores an uploaded .npz or Blender zip in the job folder; returns its path relative to that folder.

    Only bounded work here (streamed copies, zip directory and .npy headers); the dataset is loaded by
    `_check_dataset` in a validation process.
    """
    folder = job_dir(settings, job_id)
    shown_name = sanitize_filename(upload.filename or "dataset", "dataset")
    if shown_name.lower().endswith(".npz"):
        save_stream(upload.file, folder / DATASET_NPZ)
        check_npz_headers(folder / DATASET_NPZ, "dataset", shown_name, settings)
        return DATASET_NPZ
    archive = folder / DATASET_ZIP
    save_stream(upload.file, archive)
    extract_zip(archive, folder / DATASET_DIR, settings)
    archive.unlink()
    root = find_dataset_root(folder / DATASET_DIR)
    return str(root.relative_to(folder))


def _check_dataset(job_id: str, path: Path, field: str, settings: ServiceSettings) -> None:
    """load_dataset in a validation process, reading only inside the job's folder: 422 naming the frame
    or file, 413 for a limit."""
    within = str(job_dir(settings, job_id))
    check_isolated("dataset", {"path": str(path), "field": field, "within": within}, settings)


def create_nerf(
    store: JobStore,
    executor: Executor,
    settings: ServiceSettings,
    client: Client,
    inputs: NerfInputs,
    scene_child: SceneChild | None = None,
) -> Job:
    """Checks the options and the training data and queues the NeRF job (recorded on its scene when it is
    one's child)."""
    if (inputs.dataset is None) == (inputs.reconstruction_id is None):
        raise invalid("dataset: give either an uploaded dataset or reconstruction_id, exactly one")
    config = inputs.train.train_config(settings)
    webhook_url = webhooks.check_url(inputs.webhook_url, settings)
    job_id = new_job_id()
    params = NerfParams(train_config=config)
    source_job_id = inputs.reconstruction_id
    if source_job_id is not None:
        source = find_job(store, source_job_id, JobKind.reconstruction, client)
        if source.state != JobState.succeeded:
            raise conflict(
                f"reconstruction {source_job_id} is {source.state}; a NeRF trains on a succeeded one"
            )
        _check_dataset(source_job_id, output_dir(settings, source_job_id), "reconstruction_id", settings)
    with removed_on_failure(job_dir(settings, job_id)):
        if inputs.dataset is not None:
            params.dataset = _save_dataset(inputs.dataset, job_id, settings)
            _check_dataset(job_id, job_dir(settings, job_id) / params.dataset, "dataset", settings)
        job = store.create(
            JobKind.nerf,
            params,
            job_id=job_id,
            source_job_id=source_job_id,
            webhook_url=webhook_url,
            owner=client.name,
            scene_child=scene_child,
        )
    executor.submit(job_id)
    return job


def run_checkpoints(run_dir: Path) -> list[Any]:
    """The checkpoints of a NeRF run folder, oldest first (none while it has not saved one)."""
    from neural import list_checkpoints
    from neural.errors import CheckpointError, DatasetError

    if not run_dir.is_dir():
        return []
    try:
        return sorted(list_checkpoints(run_dir), key=lambda c: c.step)
    except (DatasetError, CheckpointError):
        return []


def require_checkpoint(job_id: str, settings: ServiceSettings) -> Path:
    """The NeRF job's run folder; 409 while it has no checkpoint."""
    run_dir = output_dir(settings, job_id)
    if not run_checkpoints(run_dir):
        raise conflict(f"NeRF job {job_id} has no checkpoint yet")
    return run_dir


def camera_path_of(
    store: JobStore, settings: ServiceSettings, job_id: str, num_frames: int
) -> dict[str, Any]:
    """neural.inference.camera_path of the NeRF job's run: how the photos were taken, the default view and a
    path of num_frames poses through the cameras; 409 before training started, 422 without registered
    cameras."""
    from neural.camera_path import CameraPathError
    from neural.errors import CheckpointError
    from neural.inference import camera_path

    find_job(store, job_id, JobKind.nerf)
    try:
        return camera_path(output_dir(settings, job_id), num_frames)
    except CheckpointError:
        raise conflict(f"NeRF job {job_id} has not started training") from None
    except CameraPathError as error:
        raise invalid(f"NeRF job {job_id}: {error}") from None


def check_render_size(pixels: int, settings: ServiceSettings) -> None:
    """422 for a render or video frame over SFMNERF_MAX_RENDER_PIXELS."""
    if pixels > settings.max_render_pixels:
        raise invalid(
            f"width x height = {pixels} pixels, more than the limit "
            f"SFMNERF_MAX_RENDER_PIXELS={settings.max_render_pixels}"
        )


def check_video(video: VideoParams, settings: ServiceSettings) -> None:
    """A video's frame size (422) and its frames x pixels budget SFMNERF_MAX_VIDEO_PIXELS (413)."""
    check_render_size(video.width * video.height, settings)
    if video.pixels > settings.max_video_pixels:
        raise ServiceError(
            413,
            f"num_frames x width x height = {video.pixels} pixels, more than the video budget "
            f"SFMNERF_MAX_VIDEO_PIXELS={settings.max_video_pixels}",
        )


def queue_evaluation(
    store: JobStore,
    executor: Executor,
    nerf_job_id: str,
    evaluation: EvaluationParams,
    scene_child: SceneChild | None = None,
) -> Job:
    """Held-out renders of the NeRF job's latest checkpoint scored against its data (a scene's last stage),
    owned by the NeRF job's owner."""
    source = find_job(store, nerf_job_id, JobKind.nerf)
    job = store.create(
        JobKind.evaluation, evaluation, source_job_id=nerf_job_id, owner=source.owner, scene_child=scene_child
    )
    executor.submit(job.id)
    return job


def queue_video(
    store: JobStore,
    executor: Executor,
    settings: ServiceSettings,
    nerf_job_id: str,
    video: VideoParams,
    scene_child: SceneChild | None = None,
) -> Job:
    """An orbit video job of the NeRF job's latest checkpoint (owned by the NeRF job's owner)."""
    source = find_job(store, nerf_job_id, JobKind.nerf)
    check_video(video, settings)
    require_checkpoint(nerf_job_id, settings)
    job = store.create(
        JobKind.video, video, source_job_id=nerf_job_id, owner=source.owner, scene_child=scene_child
    )
    executor.submit(job.id)
    return job
