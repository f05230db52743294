"""The heavy checks of an upload (decoding images, parsing match files, loading a dataset) in a child process.

`check_isolated(check, arguments, settings)` runs `python -m service.validation CHECK API_PID` with the
arguments as JSON on stdin; the child dies with the API (service.child_processes), limits its own address
space (SFMNERF_VALIDATION_MEMORY_BYTES) and Pillow's pixel limit (SFMNERF_MAX_IMAGE_PIXELS) before it
reads anything, and prints its verdict as one JSON line. So a
decompression bomb or a huge dataset costs the child its memory, never the API. At most
SFMNERF_VALIDATION_WORKERS children run at once (one per upload); an upload finding them all busy gets 429.

The cheap part stays in the API: the .npy headers inside an .npz and the image headers of a dataset
folder, read before anything is inflated, give the memory loading the dataset needs; an upload that would
need more than the child may have is refused there, so no accepted dataset meets the child's limit.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import resource
import subprocess
import sys
import threading
import warnings
import zipfile
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from service.child_processes import become_child_of
from service.errors import busy
from service.settings import WORKER_SETTINGS_ENV, ServiceSettings
from service.uploads import UploadRejected, decode_image, invalid, too_large, without_server_paths
from service.video_uploads import check_input_video

log = logging.getLogger(__name__)
NPZ_MEMBER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}\.npy$")
NPZ_HEADER_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}
STDERR_TAIL_CHARS = 2000
OUT_OF_MEMORY_EXIT = 3
RETRY_AFTER_SECONDS = 5
VALIDATION_BASE_BYTES = 192 * 2**20
"""Address space of a validation process before it loads a dataset: Python, numpy and Pillow (the checks of
the real data pass with 143-205 MiB: benchmarks/bench_upload_memory.py --address-space)."""
NPZ_LOADED_EXTRA_BYTES = 12
"""load_npz holds each element as given plus three float32 copies (converted, clipped, stacked)."""
CHECK_IMAGE_SIDE = 64
"""The check decodes every image file whole but keeps it at most this large: its memory does not grow
with the photos' resolution, only with the largest one's."""
IMAGE_KEPT_BYTES_PER_PIXEL = 24
"""A kept (shrunk) image: its RGB float32 pixels (12 bytes) and their copy in the stacked array (12)."""
IMAGE_DECODING_BYTES_PER_PIXEL = 32
"""The one image being decoded: 8-bit RGBA (4), its float32 (16) and the composited RGB float32 (12)."""
DATASET_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@cache
def validation_slots(workers: int) -> threading.BoundedSemaphore:
    """The API process's validation processes: SFMNERF_VALIDATION_WORKERS at most at once."""
    return threading.BoundedSemaphore(workers)


def loading_budget(settings: ServiceSettings) -> int:
    """Bytes a dataset may take once loaded, so that checking it fits in the validation process."""
    return settings.validation_memory_bytes - VALIDATION_BASE_BYTES


def check_loading_memory(needed: int, what: str, settings: ServiceSettings) -> None:
    if needed > loading_budget(settings):
        raise too_large(
            f"{what} needs about {needed // 2**20} MiB once loaded, more than the "
            f"{loading_budget(settings) // 2**20} MiB that the limit "
            f"SFMNERF_VALIDATION_MEMORY_BYTES={settings.validation_memory_bytes} leaves for a dataset"
        )


def folder_loading_bytes(folder: Path, settings: ServiceSettings) -> int:
    """The memory the check of a dataset whose files lie in folder needs for its images, from their
    headers (no pixel is decoded): the largest decoded whole, every one kept at CHECK_IMAGE_SIDE."""
    from PIL import Image

    kept = largest = 0
    images = [p for p in folder.rglob("*") if p.suffix.lower() in DATASET_IMAGE_SUFFIXES and p.is_file()]
    for path in images[: settings.max_zip_entries]:
        try:
            with Image.open(path) as image:
                pixels = image.size[0] * image.size[1]
        except Image.DecompressionBombError:
            pixels = settings.max_image_pixels + 1
        except (OSError, SyntaxError, ValueError):
            continue  # not an image: the validation process names it if the dataset uses it
        kept += min(pixels, CHECK_IMAGE_SIDE**2) * IMAGE_KEPT_BYTES_PER_PIXEL
        largest = max(largest, pixels * IMAGE_DECODING_BYTES_PER_PIXEL)
    return kept + largest


def check_npz_headers(path: Path, field: str, shown_name: str, settings: ServiceSettings) -> None:
    """Member names, dtypes and shapes of an .npz from its zip directory and .npy headers only.

    Refuses object arrays (pickles), arrays whose declared size exceeds the zip limit, and image stacks
    whose images exceed the pixel limit, before any array data is decompressed.
    """
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as error:
        raise invalid(f"{field}: {shown_name} is not a valid .npz file ({error})") from None
    with archive:
        infos = archive.infolist()
        if len(infos) > settings.max_zip_entries:
            raise too_large(
                f"{field}: {shown_name} holds {len(infos)} arrays, more than the limit "
                f"SFMNERF_MAX_ZIP_ENTRIES={settings.max_zip_entries}"
            )
        total = loaded = 0
        for info in infos:
            if not NPZ_MEMBER.match(info.filename):
                raise invalid(f"{field}: {shown_name} member {info.filename!r} is not a named .npy array")
            shape, dtype = _npy_header(archive, info, field, shown_name)
            what = f"{field}: {shown_name} array {info.filename.removesuffix('.npy')!r}"
            if dtype.hasobject:
                raise invalid(f"{what} holds Python objects; only numeric arrays are accepted")
            total += math.prod(shape) * dtype.itemsize
            loaded += math.prod(shape) * (dtype.itemsize + NPZ_LOADED_EXTRA_BYTES)
            if total > settings.max_zip_uncompressed_bytes:
                raise too_large(
                    f"{what} {shape} of {dtype} makes the arrays larger than the limit "
                    f"SFMNERF_MAX_ZIP_UNCOMPRESSED_BYTES={settings.max_zip_uncompressed_bytes}"
                )
            if (
                info.filename == "images.npy"
                and len(shape) == 4
                and shape[1] * shape[2] > settings.max_image_pixels
            ):
                raise too_large(
                    f"{what}: images of {shape[2]}x{shape[1]} pixels, more than the limit "
                    f"SFMNERF_MAX_IMAGE_PIXELS={settings.max_image_pixels}"
                )
        check_loading_memory(loaded, f"{field}: {shown_name}", settings)


def _npy_header(
    archive: zipfile.ZipFile, info: zipfile.ZipInfo, field: str, shown_name: str
) -> tuple[tuple[int, ...], np.dtype]:
    try:
        with archive.open(info) as member:
            version = np.lib.format.read_magic(member)
            reader = NPZ_HEADER_READERS.get(version)
            if reader is None:
                raise ValueError(f".npy format version {version} is not accepted")
            shape, _fortran_order, dtype = reader(member)
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as error:
        raise invalid(
            f"{field}: {shown_name} member {info.filename!r} has no valid .npy header ({error})"
        ) from None
    return tuple(int(n) for n in shape), dtype


# ---- the checks that run in the child ------------------------------------------------------------------


def _check_dataset(arguments: dict[str, Any], settings: ServiceSettings) -> None:
    """load_dataset on the extracted upload (or a reconstruction's output): every file and pose checked,
    every file it names inside `within` (the job folder)."""
    from PIL import Image

    from neural.data import ImageSize, load_dataset
    from neural.errors import DatasetError

    field = arguments["field"]
    try:
        shrunk = ImageSize(max_side=CHECK_IMAGE_SIDE)
        load_dataset(Path(arguments["path"]), image_size=shrunk, within=Path(arguments["within"]))
    except DatasetError as error:
        if isinstance(error.__cause__, (Image.DecompressionBombError, Image.DecompressionBombWarning)):
            raise too_large(f"{field}: {error} (SFMNERF_MAX_IMAGE_PIXELS)") from None
        raise invalid(f"{field}: {error}") from None


def _check_reconstruction_inputs(arguments: dict[str, Any], settings: ServiceSettings) -> None:
    """Every image decoded and every match file parsed against the image ids and size."""
    from estimation.errors import InputError
    from estimation.io.matchfile import parse_match_file

    folder = Path(arguments["folder"])
    for name in arguments["images"]:
        decode_image(folder / name, name)
    for name, index in arguments["matches"]:
        target = folder / name
        try:
            parse_match_file(
                target, index, set(arguments["image_ids"]), arguments["width"], arguments["height"]
            )
        except InputError as error:
            raise invalid(f"matches: {str(error).replace(str(target), name)}") from None


CHECKS: dict[str, Callable[[dict[str, Any], ServiceSettings], None]] = {
    "dataset": _check_dataset,
    "reconstruction_inputs": _check_reconstruction_inputs,
    "input_video": check_input_video,
}


def check_isolated(check: str, arguments: dict[str, Any], settings: ServiceSettings) -> None:
    """Runs CHECKS[check] in a child process; raises its UploadRejected, 413 when it would run or ran out
    of memory or time, 429 when every validation slot is busy. `arguments["field"]` names the request
    field in those messages."""
    field = arguments.get("field", "upload")
    if check == "dataset" and Path(arguments["path"]).is_dir():
        needed = folder_loading_bytes(Path(arguments["within"]), settings)  # the files it may name
        check_loading_memory(needed, f"{field}: the dataset's images", settings)
    slots = validation_slots(settings.validation_workers)
    if not slots.acquire(blocking=False):
        raise busy(
            f"{field}: all {settings.validation_workers} upload checks are busy "
            f"(SFMNERF_VALIDATION_WORKERS); retry after {RETRY_AFTER_SECONDS} s",
            RETRY_AFTER_SECONDS,
        )
    try:
        _run_check(check, arguments, field, settings)
    finally:
        slots.release()


def _run_check(check: str, arguments: dict[str, Any], field: str, settings: ServiceSettings) -> None:
    env = {k: v for k, v in os.environ.items() if k != "SFMNERF_API_TOKEN"}
    env[WORKER_SETTINGS_ENV] = settings.to_worker_json()
    # One malloc arena: each thread's own arena (the parent watchdog's) would reserve 64 MiB of the limit.
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MALLOC_ARENA_MAX="1")
    try:
        child = subprocess.run(
            [sys.executable, "-m", "service.validation", check, str(os.getpid())],
            input=json.dumps(arguments),
            capture_output=True,
            text=True,
            timeout=settings.validation_timeout_seconds,
            env=env,
            cwd=str(Path(__file__).resolve().parents[1]),
        )
    except subprocess.TimeoutExpired:
        raise too_large(
            f"{field}: checking the upload took longer than the limit "
            f"SFMNERF_VALIDATION_TIMEOUT_SECONDS={settings.validation_timeout_seconds:g}"
        ) from None
    lines = child.stdout.strip().splitlines()
    if child.returncode == 0 and lines:
        verdict = json.loads(lines[-1])
        if verdict["status"] == 200:
            return
        raise UploadRejected(verdict["status"], without_server_paths(verdict["detail"], settings))
    log.error("validation %s exited with %s: %s", check, child.returncode, child.stderr[-STDERR_TAIL_CHARS:])
    if child.returncode == OUT_OF_MEMORY_EXIT or child.returncode < 0:  # a signal: the kernel's OOM killer
        raise too_large(
            f"{field}: checking the upload needs more memory than the limit "
            f"SFMNERF_VALIDATION_MEMORY_BYTES={settings.validation_memory_bytes}"
        )
    raise invalid(f"{field}: the upload could not be read")


def main(check: str, parent_pid: int) -> int:
    settings = ServiceSettings.model_validate_json(os.environ[WORKER_SETTINGS_ENV])
    become_child_of(parent_pid, settings.data_dir)
    limit = settings.validation_memory_bytes
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    from PIL import Image

    Image.MAX_IMAGE_PIXELS = settings.max_image_pixels
    warnings.simplefilter("error", Image.DecompressionBombWarning)
    arguments = json.loads(sys.stdin.read())
    try:
        CHECKS[check](arguments, settings)
        verdict = {"status": 200}
    except UploadRejected as rejected:
        verdict = {"status": rejected.status_code, "detail": rejected.detail}
    except MemoryError:
        return OUT_OF_MEMORY_EXIT
    print(json.dumps(verdict))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2])))
