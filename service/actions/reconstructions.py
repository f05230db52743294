"""Creating a reconstruction job: the photos, match files and calibration stored and checked, then queued."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Literal

from estimation.config import ReconstructionConfig
from service import webhooks
from service.auth import Client
from service.executor import Executor
from service.kinds import JobKind
from service.layout import input_dir, job_dir
from service.params import ReconstructionParams
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job, new_job_id
from service.uploads import inside, invalid, removed_on_failure, sanitize_filename, save_images, save_stream
from service.validation import check_isolated
from service.video_uploads import is_video_upload, save_video

MATCH_NAME = re.compile(r"^matching(\d+)\.txt$")
CALIBRATION_NAME = "calibration.txt"
CALIBRATION_READ_BYTES = 64 * 1024

ImageSizeCheck = Callable[[int, int], None]
"""Called with the photos' width and height before the job is created (may refuse them)."""


@dataclass
class InputFile:
    """A file of a request: the name the client gave it and its content."""

    filename: str | None
    file: BinaryIO
    content_type: str | None = None


@dataclass
class ReconstructionInputs:
    """Everything a reconstruction job reads, as the client sent it."""

    images: list[InputFile]
    matches: list[InputFile] = field(default_factory=list)
    calibration: InputFile | None = None
    K: str | None = None
    features: Literal["auto", "matches", "sift"] = "auto"
    ransac_threshold_px: float | None = None
    ba_max_iterations: int | None = None
    webhook_url: str | None = None


def _parse_k(text: str, source: str) -> None:
    from estimation.errors import InputError
    from estimation.io.images import parse_calibration

    try:
        parse_calibration(text, source)
    except InputError as error:
        raise invalid(f"calibration: {error}") from None


def _k_from_numbers(numbers: str) -> str:
    """'fx 0 cx 0 fy cy 0 0 1' (commas, semicolons or spaces) -> calibration.txt text, 3 rows."""
    tokens = [t for t in re.split(r"[\s,;\[\]]+", numbers) if t]
    if len(tokens) != 9:
        raise invalid(f"K: expected 9 numbers (the 3x3 matrix row by row), found {len(tokens)}")
    return "\n".join(" ".join(tokens[row * 3 : row * 3 + 3]) for row in range(3)) + "\n"


def _store_calibration(folder: Path, calibration: InputFile | None, K: str | None) -> None:
    """calibration.txt from the file or the 9 numbers of K, checked; none when neither is given."""
    if calibration is not None and K:
        raise invalid("calibration: give either the calibration file or K, not both")
    if calibration is not None:
        text = calibration.file.read(CALIBRATION_READ_BYTES).decode("utf-8", errors="replace")
        source = sanitize_filename(calibration.filename or CALIBRATION_NAME, "calibration")
    elif K:
        text, source = _k_from_numbers(K), "K"
    else:   # no calibration: the reconstruction takes the focal length from EXIF or a prior, and refines it
        return
    _parse_k(text, source)
    inside(folder, CALIBRATION_NAME).write_text(text)


def _store_video(folder: Path, settings: ServiceSettings, inputs: ReconstructionInputs) -> None:
    """Saves the one uploaded video and probes it in the validation process; UploadRejected when refused."""
    if inputs.matches:
        raise invalid("matches: match files go with photos, not with a video")
    video = save_video(inputs.images, folder, settings)
    check_isolated("input_video", {"field": "images", "path": str(folder / video.name), "name": video.name},
                   settings)
    _store_calibration(folder, inputs.calibration, inputs.K)


def _store_inputs(
    folder: Path, settings: ServiceSettings, inputs: ReconstructionInputs
) -> tuple[int, int] | None:
    """Saves and checks everything the reconstruction reads; UploadRejected on the first problem.
    Returns the photos' (width, height); None for a video, whose keyframes' size is known only once the
    reconstruction has decoded them."""
    if any(is_video_upload(upload) for upload in inputs.images):
        _store_video(folder, settings, inputs)
        return None
    saved = save_images(((f.filename, f.file) for f in inputs.images), folder, settings)
    if len(saved) < 2:
        raise invalid(f"images: {len(saved)} image(s) uploaded, a reconstruction needs at least 2")
    first = saved[0]
    for image in saved[1:]:
        if (image.width, image.height) != (first.width, first.height):
            raise invalid(
                f"images: {image.name} is {image.width}x{image.height} but {first.name} is "
                f"{first.width}x{first.height}; all images must have the same size"
            )
    _store_calibration(folder, inputs.calibration, inputs.K)

    if inputs.features == "matches" and not inputs.matches:
        raise invalid("matches: features='matches' needs the matching<i>.txt files")
    match_files = []
    for upload in inputs.matches:
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
    return first.width, first.height


def create_reconstruction(
    store: JobStore,
    executor: Executor,
    settings: ServiceSettings,
    client: Client,
    inputs: ReconstructionInputs,
    check_image_size: ImageSizeCheck | None = None,
) -> Job:
    """Stores and checks the inputs in a new job folder and queues the reconstruction; nothing is left
    behind when any check refuses them."""
    webhook_url = webhooks.check_url(inputs.webhook_url, settings)
    job_id = new_job_id()
    folder = input_dir(settings, job_id)
    with removed_on_failure(job_dir(settings, job_id)):
        folder.mkdir(parents=True)
        size = _store_inputs(folder, settings, inputs)
        if check_image_size is not None and size is not None:
            check_image_size(*size)
        config = ReconstructionConfig(features=inputs.features).model_dump(mode="json")
        if inputs.ransac_threshold_px is not None:
            config["ransac"]["threshold_px"] = inputs.ransac_threshold_px
        if inputs.ba_max_iterations is not None:
            config["bundle_adjustment"]["max_iterations"] = inputs.ba_max_iterations
        job = store.create(
            JobKind.reconstruction,
            ReconstructionParams(config=config),
            job_id=job_id,
            webhook_url=webhook_url,
            owner=client.name,
        )
    executor.submit(job_id)
    return job
