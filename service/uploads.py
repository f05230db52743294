"""Safe handling of uploaded files: limits, sanitized names, verified images, safe zip extraction.

Every function writes only inside the folder it is given and raises `UploadRejected` with the HTTP status
(413 for a limit, 422 for bad content) and a message naming the field, file and limit.
"""

from __future__ import annotations

import logging
import re
import shutil
import stat
import time
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, BinaryIO

from PIL import Image, UnidentifiedImageError

from service.errors import ServiceError
from service.settings import ServiceSettings

if TYPE_CHECKING:
    from service.store.job_store import JobStore

log = logging.getLogger(__name__)

ALLOWED_IMAGE_FORMATS = {"PNG": ".png", "JPEG": ".jpg", "MPO": ".jpg"}
"""Pillow format -> suffix; MPO is what Pillow calls many camera JPEGs."""
SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")
MAX_NAME_LENGTH = 120
COPY_CHUNK = 1 << 20
DATASET_MARKER = "transforms_train.json"
SMALL_ENTRY_BYTES = 1 << 20
"""Entries up to this size may compress arbitrarily well (e.g. a blank mask) without counting as bombs."""
ORPHAN_MIN_AGE_SECONDS = 600.0


class UploadRejected(ServiceError):
    """An upload the service refuses; `status_code` is 413 (a limit) or 422 (bad content)."""


def too_large(detail: str) -> UploadRejected:
    return UploadRejected(413, detail)


def invalid(detail: str) -> UploadRejected:
    return UploadRejected(422, detail)


def sanitize_filename(name: str | None, field: str) -> str:
    """The last path component of a client's file name, reduced to [A-Za-z0-9._-]; never '', '.' or '..'."""
    base = (name or "").replace("\\", "/").split("/")[-1].strip()
    cleaned = SAFE_NAME.sub("_", base)[-MAX_NAME_LENGTH:].lstrip(".")
    if not cleaned or cleaned in {".", ".."}:
        raise invalid(f"{field}: file name {name!r} is empty or not usable")
    return cleaned


def inside(folder: Path, name: str) -> Path:
    """folder/name, refusing anything that would land outside folder."""
    target = (folder / name).resolve()
    if not target.is_relative_to(folder.resolve()):
        raise invalid(f"file name {name!r} points outside the job folder")
    return target


def save_stream(source: BinaryIO, target: Path) -> int:
    """Copies an upload to target in chunks; returns the byte count."""
    size = 0
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "xb") as out:
        while chunk := source.read(COPY_CHUNK):
            size += len(chunk)
            out.write(chunk)
    return size


@dataclass(frozen=True)
class SavedImage:
    """An image stored in the job folder: its final name and size."""

    name: str
    width: int
    height: int


def verify_image(path: Path, shown_name: str, settings: ServiceSettings) -> tuple[str, int, int]:
    """(Pillow format, width, height) of a PNG/JPEG within the pixel limit, else UploadRejected.

    Reads the header and the chunk structure only; `decode_image` decodes the pixels (in a worker).
    """
    try:
        with Image.open(path) as image:
            image_format, (width, height) = image.format, image.size
            if width * height > settings.max_image_pixels:
                raise too_large(
                    f"images: {shown_name} has {width}x{height} = {width * height} pixels, more than the "
                    f"limit SFMNERF_MAX_IMAGE_PIXELS={settings.max_image_pixels}"
                )
            if image_format not in ALLOWED_IMAGE_FORMATS:
                raise invalid(f"images: {shown_name} is {image_format}, only PNG and JPEG are accepted")
            image.verify()  # chunk structure and checksums, without decoding the pixels
    except Image.DecompressionBombError:
        raise too_large(
            f"images: {shown_name} has more pixels than the limit "
            f"SFMNERF_MAX_IMAGE_PIXELS={settings.max_image_pixels}"
        ) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise not_an_image(error, path, shown_name) from None
    return image_format, width, height


def not_an_image(error: Exception, path: Path, shown_name: str) -> UploadRejected:
    """422 for an image the decoder refused; its message (which may quote the stored path) names the
    file as the client called it."""
    reason = str(error).replace(str(path), shown_name).replace(str(path.parent), "")
    return invalid(f"images: {shown_name} is not a complete PNG/JPEG image ({reason})")


def decode_image(path: Path, shown_name: str) -> None:
    """Decodes every pixel (verify() misses truncated pixel data); heavy: run in a validation process."""
    try:
        with Image.open(path) as image:
            image.load()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise not_an_image(error, path, shown_name) from None


def check_image_count(count: int, settings: ServiceSettings) -> None:
    if count > settings.max_images:
        raise too_large(
            f"images: {count} files, more than the limit SFMNERF_MAX_IMAGES={settings.max_images}"
        )


def save_images(
    uploads: Iterable[tuple[str | None, BinaryIO]], folder: Path, settings: ServiceSettings
) -> list[SavedImage]:
    """Stores the uploaded images under sanitized, unique names after checking each one's header."""
    uploads = list(uploads)
    check_image_count(len(uploads), settings)
    saved: list[SavedImage] = []
    names: set[str] = set()
    for client_name, stream in uploads:
        name = sanitize_filename(client_name, "images")
        if name.lower() in names:
            raise invalid(f"images: two files are named {name!r}")
        target = inside(folder, name)
        save_stream(stream, target)
        image_format, width, height = verify_image(target, name, settings)
        suffix = ALLOWED_IMAGE_FORMATS[image_format]
        if target.suffix.lower() not in {suffix, ".jpeg" if suffix == ".jpg" else suffix}:
            # The reconstruction finds images by suffix: give the file the one its content has.
            renamed = inside(folder, f"{target.stem}{suffix}")
            if renamed.exists():
                raise invalid(f"images: {name} is a {image_format} and {renamed.name} exists already")
            target.rename(renamed)
            name = renamed.name
        names.add(name.lower())
        saved.append(SavedImage(name=name, width=width, height=height))
    return saved


# ---- dataset zips -------------------------------------------------------------------------------------


def _entry_problem(info: zipfile.ZipInfo) -> str | None:
    name = info.filename
    path = PurePosixPath(name.replace("\\", "/"))
    if name.startswith(("/", "\\")) or re.match(r"^[A-Za-z]:", name):
        return "has an absolute path"
    if ".." in path.parts:
        return "climbs out of the archive with '..'"
    if stat.S_ISLNK(info.external_attr >> 16):
        return "is a symbolic link"
    return None


def extract_zip(archive: Path, folder: Path, settings: ServiceSettings, field: str = "dataset") -> None:
    """Extracts a zip into folder, refusing traversal, absolute names, links and bombs."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as error:
        raise invalid(f"{field}: not a valid zip archive ({error})") from None
    with zf:
        infos = [info for info in zf.infolist() if not info.filename.startswith("__MACOSX/")]
        if len(infos) > settings.max_zip_entries:
            raise too_large(
                f"{field}: the zip holds {len(infos)} entries, more than the limit "
                f"SFMNERF_MAX_ZIP_ENTRIES={settings.max_zip_entries}"
            )
        declared = sum(info.file_size for info in infos)
        if declared > settings.max_zip_uncompressed_bytes:
            raise too_large(
                f"{field}: the zip expands to {declared} bytes, more than the limit "
                f"SFMNERF_MAX_ZIP_UNCOMPRESSED_BYTES={settings.max_zip_uncompressed_bytes}"
            )
        for info in infos:
            problem = _entry_problem(info)
            if problem:
                raise invalid(f"{field}: zip entry {info.filename!r} {problem}; refused")
            ratio = info.file_size / max(info.compress_size, 1)
            if ratio > settings.max_zip_ratio and info.file_size > SMALL_ENTRY_BYTES:
                raise too_large(
                    f"{field}: zip entry {info.filename!r} is compressed {ratio:.0f}:1, more than the "
                    f"zip-bomb limit SFMNERF_MAX_ZIP_RATIO={settings.max_zip_ratio:g}"
                )
        budget = settings.max_zip_uncompressed_bytes
        for info in infos:
            target = (folder / info.filename).resolve()
            if not target.is_relative_to(folder.resolve()):
                raise invalid(f"{field}: zip entry {info.filename!r} points outside the job folder; refused")
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            budget -= _extract_entry(zf, info, target, min(info.file_size, budget), field)


def _extract_entry(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, allowed: int, field: str) -> int:
    """Writes one entry, stopping once it exceeds `allowed` bytes (headers may lie); returns bytes written."""
    written = 0
    try:
        with zf.open(info) as source, open(target, "wb") as out:
            while chunk := source.read(COPY_CHUNK):
                written += len(chunk)
                if written > allowed:
                    raise too_large(
                        f"{field}: zip entry {info.filename!r} expands beyond its declared size or the limit "
                        "SFMNERF_MAX_ZIP_UNCOMPRESSED_BYTES"
                    )
                out.write(chunk)
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as error:
        raise invalid(f"{field}: zip entry {info.filename!r} cannot be extracted ({error})") from None
    return written


def find_dataset_root(folder: Path, field: str = "dataset") -> Path:
    """The folder of an extracted Blender dataset: the top level or the single folder holding its json."""
    if (folder / DATASET_MARKER).is_file():
        return folder
    candidates = sorted(p.parent for p in folder.glob(f"*/{DATASET_MARKER}"))
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise invalid(f"{field}: the zip holds no {DATASET_MARKER} (expected a Blender-format NeRF dataset)")
    raise invalid(f"{field}: the zip holds several datasets ({', '.join(p.name for p in candidates)})")


def remove_tree(folder: Path) -> None:
    shutil.rmtree(folder, ignore_errors=True)


@contextmanager
def removed_on_failure(folder: Path) -> Iterator[None]:
    """Removes a new job's folder when its submission fails in any way (a refusal or a bug)."""
    try:
        yield
    except BaseException:
        remove_tree(folder)
        raise


def sweep_orphan_folders(jobs_dir: Path, store: JobStore) -> list[str]:
    """Removes job folders that have no job in the store (a submission that died half-way).

    Only folders untouched for ORPHAN_MIN_AGE_SECONDS: another server on the same data folder may be
    storing an upload whose job it has not created yet.
    """
    removed = []
    now = time.time()
    for folder in sorted(jobs_dir.iterdir()) if jobs_dir.is_dir() else []:
        if not folder.is_dir() or now - folder.stat().st_mtime < ORPHAN_MIN_AGE_SECONDS:
            continue
        if store.get(folder.name) is None:
            remove_tree(folder)
            removed.append(folder.name)
    if removed:
        log.warning("removed %d job folder(s) without a job: %s", len(removed), ", ".join(removed))
    return removed


def without_server_paths(text: str, settings: ServiceSettings) -> str:
    """A message for a client: paths inside a job folder shortened to the names the client gave, and
    any other path of the data folder hidden."""
    job_files = re.escape(str(settings.jobs_dir)) + r"/[0-9a-f]{32}/(?:input/(?:dataset/)?|output/)?"
    return re.sub(job_files, "", text).replace(str(settings.data_dir), "<data>")
