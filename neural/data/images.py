"""Image files as float RGB arrays: RGBA composited once, loaded smaller on request, resized files cached.

Images can be loaded at a reduced size (`ImageSize`, intrinsics scaled with them by the loaders), resized
files cached by content key.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from neural.errors import DatasetError

#: Bumped when the cached resized images would change.
IMAGE_CACHE_VERSION = 1


@dataclass(frozen=True)
class ImageSize:
    """Load images smaller: at most `max_side` pixels on their longer side, or `downscale` times smaller."""

    max_side: int | None = None
    downscale: float | None = None

    def target(self, width: int, height: int) -> tuple[int, int]:
        """(W', H') = round(s W), round(s H), s = min(1, max_side / max(W, H)) or 1 / downscale."""
        scale = 1.0
        if self.max_side is not None:
            scale = min(scale, self.max_side / max(width, height))
        if self.downscale is not None:
            scale = min(scale, 1.0 / self.downscale)
        return max(1, round(width * scale)), max(1, round(height * scale))


def load_image(path: Path, white_background: bool) -> np.ndarray:
    """RGB(A) image file -> (H,W,3) float32 in [0,1]; RGBA is composited: rgb a + background (1 - a)."""
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    try:
        with Image.open(path) as image:
            has_alpha = image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info)
            pixels = np.asarray(image.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as error:
        # Above Pillow's MAX_IMAGE_PIXELS (a warning becomes this error where warnings are errors).
        raise DatasetError(f"{path}: more pixels than the limit {Image.MAX_IMAGE_PIXELS}") from error
    except OSError as error:
        raise DatasetError(f"{path}: cannot read image ({error})") from None
    if not has_alpha:
        return pixels
    rgb, alpha = pixels[..., :3], pixels[..., 3:]
    background = 1.0 if white_background else 0.0
    return rgb * alpha + background * (1.0 - alpha)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H,W,C) float image resampled to (height, width, C) by area averaging (PIL's box filter)."""
    if image.shape[:2] == (height, width):
        return image
    channels = [
        np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c], np.float32), mode="F").resize(
            (width, height), Image.Resampling.BOX
        ))
        for c in range(image.shape[-1])
    ]  # fmt: skip
    return np.stack(channels, axis=-1)


@dataclass(frozen=True)
class ImageLoading:
    """How a loader reads image files: the RGBA background, an optional smaller size, a cache folder."""

    white_background: bool = True
    image_size: ImageSize | None = None
    cache_dir: Path | None = None

    def size_for(self, width: int, height: int) -> tuple[int, int]:
        return (width, height) if self.image_size is None else self.image_size.target(width, height)

    def load(self, path: Path) -> tuple[np.ndarray, tuple[int, int]]:
        """The image at its loading size and its file's (width, height).

        Resized images are rounded to float16 (whether cached or not, so both give the same values) and,
        with a cache_dir, kept as CACHE/<key>.npy; the key hashes the file's path, size and mtime, the
        target size and the background, so a changed file is decoded afresh.
        """
        if self.image_size is None:  # full size: load_image's own checks and errors, nothing else
            image = load_image(path, self.white_background)
            return image, (image.shape[1], image.shape[0])
        if not path.is_file():
            raise DatasetError(f"{path}: image file not found")
        try:
            with Image.open(path) as header:
                original = header.size
        except (Image.DecompressionBombError, Image.DecompressionBombWarning) as error:
            raise DatasetError(f"{path}: more pixels than the limit {Image.MAX_IMAGE_PIXELS}") from error
        except OSError as error:
            raise DatasetError(f"{path}: cannot read image ({error})") from None
        width, height = self.size_for(*original)
        if (width, height) == original:
            return load_image(path, self.white_background), original
        cached = None
        if self.cache_dir is not None:
            stat = path.stat()
            key = json.dumps(
                [IMAGE_CACHE_VERSION, str(path.resolve()), stat.st_size, stat.st_mtime_ns, width, height,
                 self.white_background]
            )  # fmt: skip
            cached = self.cache_dir / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.npy"
            if cached.is_file():
                return np.load(cached).astype(np.float32), original
        small = resize_image(load_image(path, self.white_background), width, height).astype(np.float16)
        if cached is not None:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            temporary = cached.with_suffix(".tmp.npy")
            np.save(temporary, small)
            temporary.replace(cached)
        return small.astype(np.float32), original


def check_same_size(image: np.ndarray, name: str, first: np.ndarray, first_name: str) -> None:
    """DatasetError naming `name` if its size differs from the first image's."""
    if image.shape != first.shape:
        raise DatasetError(
            f"{name}: image size {image.shape[1]}x{image.shape[0]} differs from "
            f"{first.shape[1]}x{first.shape[0]} of {first_name}; all images must have one size"
        )
