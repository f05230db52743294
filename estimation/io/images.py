"""The images folder and the calibration: which images, their ids and size, the 3x3 K, and what the
photos' EXIF says about the focal length.

Images are used as they are displayed: the EXIF orientation is applied when loading (and the width and
height of a rotated photo swap), so pixels, K and every output refer to the upright image.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import NamedTuple

import numpy as np
from PIL import ExifTags, Image, ImageOps, UnidentifiedImageError

from estimation.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Files with these suffixes (any case) are images; everything else in the folder is ignored."""
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".webm", ".avi")
"""Files with these suffixes (any case) are read as videos (`estimation.io.video`)."""
CALIBRATION_FILE_NAME = "calibration.txt"
DISTORTION_FILE_NAME = "distortion.json"
"""Written by `sfmnerf calibrate` next to calibration.txt; read with it (the OPENCV model, held fixed)."""
DISTORTION_COEFFICIENTS = ("k1", "k2", "p1", "p2")
MIN_IMAGES = 2
K_LAST_ROW_TOLERANCE = 1e-9
SINGULAR_CONDITION = 1e12
"""K whose condition number exceeds this is treated as singular."""
ROTATED_ORIENTATIONS = (5, 6, 7, 8)
"""EXIF orientations that turn the stored image by 90 degrees (width and height swap)."""
FULL_FRAME_DIAGONAL_MM = float(np.hypot(36.0, 24.0))
"""The 35 mm equivalent focal length is defined on the diagonal of a 36x24 mm frame (CIPA DC-008)."""
MM_PER_RESOLUTION_UNIT = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}
"""EXIF FocalPlaneResolutionUnit -> millimetres (1: none, read as inches as the standard's default)."""
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_CHUNK_HEADER = struct.Struct(">I4s")
"""A PNG chunk's data length and type; its data and a 4-byte CRC follow."""


@dataclass(frozen=True)
class ImageSet:
    """The images of a folder, in a fixed order: image index -> path, file name and numeric id."""

    folder: Path
    paths: list[Path]
    width: int
    height: int
    ids: dict[int, int] = field(default_factory=dict)    # numeric file stem -> image index

    @cached_property
    def names(self) -> list[str]:
        """File names by image index (computed once: reports look them up per pair)."""
        return [path.name for path in self.paths]

    def __len__(self) -> int:
        return len(self.paths)


def _sort_key(path: Path) -> tuple[int, float, str]:
    """Numeric stems first, by value (2.png before 10.png); then the rest by name."""
    stem = path.stem
    return (0, int(stem), path.name) if stem.isdigit() else (1, 0.0, path.name)


def _png_exif_after_pixels(path: Path) -> bool:
    """Whether the PNG file has an eXIf chunk after its first IDAT (pixel data) chunk, read from the chunk
    headers alone."""
    with open(path, "rb") as file:
        if file.read(len(PNG_SIGNATURE)) != PNG_SIGNATURE:
            return False
        seen_pixels = False
        while len(header := file.read(PNG_CHUNK_HEADER.size)) == PNG_CHUNK_HEADER.size:
            length, kind = PNG_CHUNK_HEADER.unpack(header)
            if kind == b"eXIf" and seen_pixels:
                return True
            if kind == b"IEND":
                return False
            seen_pixels |= kind == b"IDAT"
            file.seek(length + 4, 1)
    return False


def _exif(image: Image.Image, path: Path) -> Image.Exif:
    """The EXIF of the image opened from `path`, its pixels not decoded: PIL decodes a whole PNG to look
    for an eXIf chunk after the pixel data (0.05 s for lego's 90 small PNGs), so it is asked only when the
    chunk headers show one there."""
    if image.format == "PNG" and "exif" not in image.info and not _png_exif_after_pixels(path):
        return Image.Exif()
    return image.getexif()


def _upright_size(image: Image.Image, path: Path) -> tuple[int, int]:
    """(width, height) of the image as displayed: swapped when its EXIF orientation turns it 90 degrees."""
    width, height = image.size
    rotated = _exif(image, path).get(ExifTags.Base.Orientation) in ROTATED_ORIENTATIONS
    return (height, width) if rotated else (width, height)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of the upright image (EXIF orientation applied), read from the file header;
    InputError if it is not a readable image."""
    try:
        with Image.open(path) as image:
            return _upright_size(image, path)
    except (UnidentifiedImageError, OSError) as error:
        raise InputError(f"{path}: not a readable PNG/JPEG image ({error})") from None


def list_images(folder: Path, min_images: int = MIN_IMAGES) -> ImageSet:
    """The PNG/JPEG images of `folder`, all of one size; image id = numeric file stem where present."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: images folder does not exist or is not a folder")
    paths = sorted(
        (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=_sort_key
    )
    if len(paths) < min_images:
        raise InputError(
            f"{folder}: found {len(paths)} PNG/JPEG image(s), need at least {min_images} to reconstruct"
        )
    ids: dict[int, int] = {}
    for index, path in enumerate(paths):
        if path.stem.isdigit():
            numeric_id = int(path.stem)
            if numeric_id in ids:
                other = paths[ids[numeric_id]].name
                raise InputError(f"{path}: image id {numeric_id} is also the id of {other}")
            ids[numeric_id] = index
    sizes = [image_size(path) for path in paths]
    width, height = sizes[0]
    for path, size in zip(paths, sizes, strict=True):
        if size != (width, height):
            raise InputError(
                f"{path}: image is {size[0]}x{size[1]} but {paths[0].name} is {width}x{height};"
                " all images must have the same size"
            )
    return ImageSet(folder=folder, paths=paths, width=width, height=height, ids=ids)


def load_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB pixels of an image file, upright (its EXIF orientation applied)."""
    try:
        with Image.open(path) as image:
            return np.asarray(ImageOps.exif_transpose(image).convert("RGB"))
    except (UnidentifiedImageError, OSError) as error:
        raise InputError(f"{path}: not a readable PNG/JPEG image ({error})") from None


def parse_calibration(text: str, source: str) -> np.ndarray:
    """K from 3 rows of 3 whitespace-separated numbers; InputError naming `source` and the line."""
    rows = [(number, line.split()) for number, line in enumerate(text.splitlines(), start=1) if line.strip()]
    if len(rows) != 3:
        raise InputError(f"{source}: expected a 3x3 matrix (3 rows of 3 numbers), found {len(rows)} rows")
    K = np.empty((3, 3))
    for r, (line_number, tokens) in enumerate(rows):
        if len(tokens) != 3:
            raise InputError(
                f"{source}, line {line_number}: expected 3 numbers in a row of K, found {len(tokens)}"
            )
        for c, token in enumerate(tokens):
            try:
                K[r, c] = float(token)
            except ValueError:
                raise InputError(f"{source}, line {line_number}: non-numeric value {token!r} in K") from None
            if not np.isfinite(K[r, c]):
                raise InputError(f"{source}, line {line_number}: non-finite value {token!r} in K")
    singular_values = np.linalg.svd(K, compute_uv=False)
    if singular_values[-1] * SINGULAR_CONDITION <= singular_values[0]:
        raise InputError(f"{source}: K is singular (determinant {np.linalg.det(K):.3g})")
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=K_LAST_ROW_TOLERANCE):
        raise InputError(f"{source}: the last row of K must be 0 0 1, got {' '.join(f'{x:g}' for x in K[2])}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(
            f"{source}: focal lengths K[0,0] and K[1,1] must be positive, got {K[0, 0]:g}, {K[1, 1]:g}"
        )
    return K


def load_calibration(path: Path) -> np.ndarray:
    """K (3x3) from a text file; InputError if it is missing, not 3x3, non-numeric or singular."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: calibration file not found (a 3x3 K, rows whitespace separated)")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read the calibration file ({error})") from None
    return parse_calibration(text, str(path))


def load_distortion(path: Path) -> dict[str, float]:
    """k1 k2 p1 p2 from a distortion.json written by `sfmnerf calibrate` ({"camera": {"k1": ...}})."""
    try:
        camera = json.loads(Path(path).read_text())["camera"]
        return {name: float(camera[name]) for name in DISTORTION_COEFFICIENTS}
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"{path}: expected the distortion.json of `sfmnerf calibrate` with camera "
                         f"k1 k2 p1 p2 ({type(error).__name__}: {error})") from None


def find_distortion(folder: Path, override: Path | None = None) -> dict[str, float] | None:
    """k1 k2 p1 p2 from distortion.json next to the calibration file in use, or None if there is none."""
    calibration = Path(override) if override is not None else Path(folder) / CALIBRATION_FILE_NAME
    path = calibration.parent / DISTORTION_FILE_NAME
    return load_distortion(path) if calibration.is_file() and path.is_file() else None


def find_calibration(folder: Path, override: Path | None = None) -> np.ndarray | None:
    """K from `override` when given (it must exist), else from calibration.txt in the images folder
    when there is one, else None (the camera is then calibrated from EXIF or a prior)."""
    if override is None and not (Path(folder) / CALIBRATION_FILE_NAME).exists():
        return None
    return load_calibration(Path(override) if override is not None else Path(folder) / CALIBRATION_FILE_NAME)


class ExifFocal(NamedTuple):
    """The focal length in pixels of the upright image that the EXIF gives, or why it gives none."""

    focal_px: float | None
    source: str          # "FocalLengthIn35mmFilm", "FocalLength+FocalPlaneXResolution" or "none"
    problem: str | None  # why the EXIF was not used (absent, zero, absurd field of view ...)


def _positive(value: object) -> float | None:
    """The EXIF rational/number as a finite positive float, else None."""
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if np.isfinite(number) and number > 0 else None


def exif_focal(path: Path, field_of_view_deg: tuple[float, float]) -> ExifFocal:
    """f_px = f35 / 43.27 mm * image diagonal (35 mm equivalent), else f_mm * FocalPlaneXResolution / unit
    (scaled by width / ExifImageWidth when the file was resized). A focal whose field of view across the
    larger side lies outside `field_of_view_deg` (min, max) is rejected as a lie."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            raw_width, raw_height = image.size
            width, height = _upright_size(image, path)
            exif = _exif(image, path).get_ifd(ExifTags.IFD.Exif)
    except (UnidentifiedImageError, OSError) as error:
        raise InputError(f"{path}: not a readable PNG/JPEG image ({error})") from None
    tags = ExifTags.Base
    candidates: list[tuple[str, float | None, str]] = []
    if tags.FocalLengthIn35mmFilm in exif:
        f35 = _positive(exif[tags.FocalLengthIn35mmFilm])
        focal_px = f35 / FULL_FRAME_DIAGONAL_MM * float(np.hypot(width, height)) if f35 else None
        candidates.append(("FocalLengthIn35mmFilm", focal_px,
                           f"FocalLengthIn35mmFilm = {exif[tags.FocalLengthIn35mmFilm]}"))
    if tags.FocalLength in exif and tags.FocalPlaneXResolution in exif:
        focal_mm = _positive(exif[tags.FocalLength])
        per_unit = _positive(exif[tags.FocalPlaneXResolution])
        unit_mm = MM_PER_RESOLUTION_UNIT.get(int(exif.get(tags.FocalPlaneResolutionUnit, 2)))
        exif_width = _positive(exif.get(tags.ExifImageWidth)) or raw_width
        focal_px = (focal_mm * per_unit / unit_mm * raw_width / exif_width
                    if focal_mm and per_unit and unit_mm else None)
        candidates.append(("FocalLength+FocalPlaneXResolution", focal_px,
                           f"FocalLength = {exif[tags.FocalLength]} mm, FocalPlaneXResolution = "
                           f"{exif[tags.FocalPlaneXResolution]}"))
    problems = []
    for source, focal_px, described in candidates:
        if focal_px is None:
            problems.append(f"{described} is not a positive focal length")
            continue
        fov = float(np.degrees(2 * np.arctan(max(width, height) / (2 * focal_px))))
        if not field_of_view_deg[0] <= fov <= field_of_view_deg[1]:
            problems.append(f"{described} gives an absurd field of view of {fov:.3g} deg "
                            f"(plausible: {field_of_view_deg[0]:g}..{field_of_view_deg[1]:g})")
            continue
        return ExifFocal(float(focal_px), source, None)
    return ExifFocal(None, "none", "; ".join(problems) or "no EXIF focal length")
