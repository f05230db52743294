"""Actions on scenes (photos -> poses -> radiance field -> views as child jobs): create one with every
option checked at submit time, cancel, retry from the stage that stopped, delete.

`scene_lock` serialises these with the scene supervisor's steps (service.scene_supervisor)."""

from __future__ import annotations

import tempfile
import threading
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from neural.budget import expected_seconds
from service.actions.jobs import cancel_job, delete_job, retry_job
from service.actions.nerf import TrainOptions, check_render_size, check_video
from service.actions.reconstructions import InputFile, ReconstructionInputs, create_reconstruction
from service.auth import ANONYMOUS, Client
from service.errors import conflict
from service.executor import Executor
from service.kinds import TERMINAL_STATES, JobState
from service.params import VideoParams
from service.pipeline import SceneOptions, orbit_size
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Scene, new_job_id, utcnow
from service.uploads import UploadRejected, extract_zip, invalid, sanitize_filename, save_stream

ZIP_PHOTO_SUFFIXES = {".png", ".jpg", ".jpeg"}
CHILD_JOB_FIELDS = {
    "reconstruction": ("reconstruction_job_id",),
    "nerf": ("nerf_job_id",),
    "views": ("video_job_id", "evaluation_job_id"),
}
"""The scene's columns naming each stage's child jobs."""
scene_lock = threading.Lock()
"""Serialises the supervisor's steps with the actions' cancel, retry and delete of scenes."""


def stage_jobs(scene: Scene, stage: str) -> list[str]:
    """The ids of the child jobs of one stage (those created so far)."""
    return [job_id for name in CHILD_JOB_FIELDS[stage] if (job_id := getattr(scene, name))]


def scene_owner(store: JobStore, scene: Scene) -> str | None:
    """The client a scene belongs to: the owner of its reconstruction job (the client that created it)."""
    job = store.get(scene.reconstruction_job_id) if scene.reconstruction_job_id else None
    return job.owner if job is not None else None


def owner_client(owner: str | None) -> Client:
    """Who a scene's child jobs are created as: its owner without admin rights (the anonymous admin of a
    service without tokens when it has none)."""
    return ANONYMOUS if owner is None else Client(name=owner, admin=False)


@dataclass
class SceneInputs:
    """A scene as the client sent it: the photos (files and/or a zip), the NeRF's and the views' options."""

    photos: ReconstructionInputs
    train: TrainOptions
    photos_zip: InputFile | None = None
    options: dict[str, float] = field(default_factory=dict)
    """SceneOptions fields besides train_config and expected_seconds (min_registered_images, orbit_frames,
    views_share, ...)."""


def _zip_photos(archive: InputFile, folder: Path, settings: ServiceSettings) -> dict[str, list[Path]]:
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


def check_views_fit(options: SceneOptions, width: int, height: int, settings: ServiceSettings) -> None:
    """The orbit video (frame size and frames x pixels budget) and the held-out renders of photos of this
    size fit the service's limits: refused at submit time rather than after the training."""
    orbit_width, orbit_height = orbit_size(width, height, options.orbit_max_side)
    orbit = VideoParams(num_frames=options.orbit_frames, width=orbit_width, height=orbit_height)
    check_video(orbit, settings)
    held_out_width, held_out_height = orbit_size(width, height, options.held_out_max_side)
    check_render_size(held_out_width * held_out_height, settings)


def create_scene(
    store: JobStore, executor: Executor, settings: ServiceSettings, client: Client, inputs: SceneInputs
) -> Scene:
    """Checks every option of every stage, stores the photos and queues the reconstruction; the scene
    supervisor takes it from there."""
    options = SceneOptions(train_config=inputs.train.train_config(settings), **inputs.options)
    photos = inputs.photos
    with ExitStack() as stack:
        if inputs.photos_zip is not None:
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(dir=settings.data_dir)))
            found = _zip_photos(inputs.photos_zip, folder, settings)

            def opened(path: Path) -> InputFile:
                name = sanitize_filename(path.name, "photos_zip")
                return InputFile(name, stack.enter_context(open(path, "rb")))

            photos.images = [*photos.images, *map(opened, found["images"])]
            photos.matches = [*photos.matches, *map(opened, found["matches"])]
            if photos.calibration is None and photos.K is None and found["calibration"]:
                photos.calibration = opened(found["calibration"][0])
        if not photos.images:
            raise invalid("images: upload the photos as `images` or as a `photos_zip`")
        minutes = options.train_config.get("minutes")
        expected = expected_seconds(minutes, len(photos.images), options.views_share)
        options = options.model_copy(update={"expected_seconds": expected})
        reconstruction = create_reconstruction(
            store, executor, settings, client, photos,
            check_image_size=lambda width, height: check_views_fit(options, width, height, settings),
        )  # fmt: skip
    scene = store.create_scene(
        Scene(
            id=new_job_id(),
            state=JobState.running,
            stage="reconstruction",
            params=options.model_dump(mode="json"),
            reconstruction_job_id=reconstruction.id,
            log=[],
        )
    )
    store.update_scene(scene.id, log=f"reconstruction job {reconstruction.id} started")
    return store.get_scene(scene.id)


def cancel_scene(store: JobStore, executor: Executor, settings: ServiceSettings, scene: Scene) -> None:
    """Marks a running scene cancelled and cancels its running child jobs (their processes are killed)."""
    if scene.state != JobState.running:
        raise conflict(f"scene {scene.id} is already {scene.state}")
    store.update_scene(scene.id, state=JobState.cancelled, finished_at=utcnow(), log="cancelled")
    for job_id in stage_jobs(scene, scene.stage):
        job = store.get(job_id)
        if job is not None and job.state not in TERMINAL_STATES:
            cancel_job(store, executor, settings, job_id)


def retry_scene(store: JobStore, executor: Executor, settings: ServiceSettings, scene: Scene) -> None:
    """Runs the failed or cancelled jobs of a failed or cancelled scene's stage again (new jobs); earlier
    stages stay. 409 when the stage's jobs all succeeded (a reconstruction that registered too few images
    would register as few again)."""
    if scene.state not in (JobState.failed, JobState.cancelled):
        raise conflict(f"only failed or cancelled scenes can be retried; {scene.id} is {scene.state}")
    again = {}
    for job_id in stage_jobs(scene, scene.stage):
        job = store.get(job_id)
        if job is not None and job.state in (JobState.failed, JobState.cancelled):
            again[job_id] = retry_job(store, executor, settings, job_id).id
    if scene.stage == "reconstruction" and not again:
        raise conflict(f"{scene.error}; a retry would give the same: start a scene with more photos")
    names = CHILD_JOB_FIELDS.get(scene.stage, CHILD_JOB_FIELDS["views"])
    values = {name: again.get(getattr(scene, name), getattr(scene, name)) for name in names}
    store.update_scene(
        scene.id, state=JobState.running, error=None, finished_at=None,
        log=f"retry of stage {scene.stage}" + (f": jobs {', '.join(again.values())}" if again else ""),
        **values,
    )  # fmt: skip


def delete_scene(store: JobStore, executor: Executor, settings: ServiceSettings, scene: Scene) -> None:
    """Cancels a running scene, then deletes its child jobs and the jobs they retried (files included)
    and the scene."""
    if scene.state not in TERMINAL_STATES:
        cancel_scene(store, executor, settings, scene)
    for job_id in store.scene_job_ids(scene):
        delete_job(store, executor, settings, job_id)
    store.delete_scene(scene.id)
