"""The images folder and the calibration: which images, their ids and size, and the 3x3 K."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from estimation.errors import InputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Files with these suffixes (any case) are images; everything else in the folder is ignored."""
CALIBRATION_FILE_NAME = "calibration.txt"
MIN_IMAGES = 2
K_LAST_ROW_TOLERANCE = 1e-9
SINGULAR_CONDITION = 1e12
"""K whose condition number exceeds this is treated as singular."""


@dataclass(frozen=True)
class ImageSet:
    """The images of a folder, in a fixed order: image index -> path, file name and numeric id."""

    folder: Path
    paths: list[Path]
    width: int
    height: int
    ids: dict[int, int] = field(default_factory=dict)    # numeric file stem -> image index

    @property
    def names(self) -> list[str]:
        return [path.name for path in self.paths]

    def __len__(self) -> int:
        return len(self.paths)


def _sort_key(path: Path) -> tuple[int, float, str]:
    """Numeric stems first, by value (2.png before 10.png); then the rest by name."""
    stem = path.stem
    return (0, int(stem), path.name) if stem.isdigit() else (1, 0.0, path.name)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) read from the file header; InputError if it is not a readable image."""
    try:
        with Image.open(path) as image:
            return image.size
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
    """(H, W, 3) uint8 RGB pixels of an image file."""
    try:
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))
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


def find_calibration(folder: Path, override: Path | None = None) -> np.ndarray:
    """K from `override` when given, else from calibration.txt in the images folder."""
    return load_calibration(Path(override) if override is not None else Path(folder) / CALIBRATION_FILE_NAME)
