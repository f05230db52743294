"""Photos with lens distortion (or per-photo intrinsics) become pinhole images of one camera at load time.

A reconstruction's transforms.json (nerfstudio's OPENCV model) gives the file's camera, and each frame may
give its own: fl_x fl_y cx cy k1 k2 p1 p2, with the principal point in nerfstudio's pixel convention (the
top-left pixel's centre at (0.5, 0.5)). NeRF casts pinhole rays from one K, so every photo is resampled
once into the *target*: the file's camera without distortion, zoomed just enough that each of its pixels
sees inside every photo (no invented border). The SfM code's own projection (estimation.geometry.projection,
OpenCV pixel convention) does the mapping; the conversion between the two conventions happens here, once.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from estimation.geometry.projection import Camera, transfer_pixels
from estimation.io.export import PIXEL_CENTER_SHIFT
from neural.errors import DatasetError

#: nerfstudio camera models whose parameters this loader reads (all are special cases of OPENCV).
SUPPORTED_CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
#: Distortion terms of nerfstudio's other models; a photo that sets one cannot be undistorted here.
UNSUPPORTED_TERMS = ("k3", "k4")
#: The most the target may zoom in to keep every pixel inside the photos (beyond: the distortion is absurd).
MAX_ZOOM = 2.0
#: Bisection steps for the zoom (2^-30 of MAX_ZOOM - 1: far below a pixel).
ZOOM_BISECTIONS = 30


def camera_from_transforms(
    fields: Mapping[str, Any], width: int, height: int, scale: tuple[float, float], where: str
) -> Camera:
    """The OpenCV-convention Camera of fl_x [fl_y cx cy k1 k2 p1 p2] (fl_y defaults to fl_x, the principal
    point to the image centre) for a W x H image loaded (sx, sy) times smaller: f' = s f, c'_ns = s c_ns."""
    model = fields.get("camera_model", "OPENCV")
    if model not in SUPPORTED_CAMERA_MODELS:
        raise DatasetError(
            f"{where}: camera_model {model!r} is not supported (one of {', '.join(SUPPORTED_CAMERA_MODELS)})"
        )

    def number(key: str, default: float | None = None) -> float:
        if key not in fields and default is None:
            raise DatasetError(f"{where}: missing key {key!r}")
        try:
            return float(fields.get(key, default))
        except (TypeError, ValueError):
            raise DatasetError(f"{where}: {key} is not a number: {fields[key]!r}") from None

    for term in UNSUPPORTED_TERMS:
        if number(term, 0.0) != 0.0:
            raise DatasetError(f"{where}: distortion term {term} is not supported (only k1 k2 p1 p2)")
    sx, sy = scale
    fx = number("fl_x")
    fy, cx, cy = number("fl_y", fx), number("cx", width / 2.0), number("cy", height / 2.0)
    distortion = {key: number(key, 0.0) for key in ("k1", "k2", "p1", "p2")}
    return Camera(
        "opencv" if any(distortion.values()) else "pinhole",
        fx=fx * sx, fy=fy * sy, cx=cx * sx - PIXEL_CENTER_SHIFT, cy=cy * sy - PIXEL_CENTER_SHIFT,
        **distortion,
    )  # fmt: skip


def border_pixels(width: int, height: int) -> np.ndarray:
    """Every pixel centre on the image's edge (OpenCV convention), (2 (W + H) - 4, 2)."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    edge = (u == 0) | (v == 0) | (u == width - 1) | (v == height - 1)
    return np.stack([u[edge], v[edge]], axis=-1)


def zoomed(camera: Camera, zoom: float) -> Camera:
    """The camera with its focal lengths multiplied by `zoom` (same principal point)."""
    return replace(camera, fx=camera.fx * zoom, fy=camera.fy * zoom)


def sees_inside(target: Camera, photos: Sequence[Camera], width: int, height: int) -> bool:
    """True when every edge pixel of `target` maps inside every photo (within half a pixel)."""
    edge = border_pixels(width, height)
    for photo in photos:
        uv = transfer_pixels(target, photo, edge)
        if not (np.all(uv >= -0.5) and np.all(uv[:, 0] <= width - 0.5) and np.all(uv[:, 1] <= height - 0.5)):
            return False
    return True


def pinhole_target(
    file_camera: Camera, photos: Sequence[Camera], width: int, height: int, where: str
) -> Camera:
    """The file's camera without distortion, focal times the least zoom z in [1, MAX_ZOOM] for which every
    pixel sees inside every photo (found by bisection)."""
    pinhole = file_camera.pinhole()
    if sees_inside(pinhole, photos, width, height):
        return pinhole
    if not sees_inside(zoomed(pinhole, MAX_ZOOM), photos, width, height):
        raise DatasetError(
            f"{where}: the lens distortion (or a frame's intrinsics) leaves no pinhole view inside every "
            f"photo even zoomed {MAX_ZOOM}x; check k1 k2 p1 p2 and the frames' fl_x cx cy"
        )
    low, high = 1.0, MAX_ZOOM
    for _ in range(ZOOM_BISECTIONS):
        middle = 0.5 * (low + high)
        inside = sees_inside(zoomed(pinhole, middle), photos, width, height)
        low, high = (low, middle) if inside else (middle, high)
    return zoomed(pinhole, high)


def resample_to(image: np.ndarray, photo: Camera, target: Camera) -> np.ndarray:
    """I_target(p) = I_photo(transfer_pixels(target, photo, p)), bilinear; (H,W,C) float32."""
    import cv2  # here, not at import: dataset validation runs under a memory limit that OpenCV's load breaks

    height, width = image.shape[:2]
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    uv = transfer_pixels(target, photo, np.stack([u.ravel(), v.ravel()], axis=-1)).astype(np.float32)
    map_u, map_v = uv[:, 0].reshape(height, width), uv[:, 1].reshape(height, width)
    resampled = cv2.remap(np.ascontiguousarray(image, np.float32), map_u, map_v, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)  # the zoom keeps the border within half a pixel
    return resampled.reshape(image.shape)


def to_nerfstudio_intrinsics(camera: Camera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) with the principal point in nerfstudio's convention, as Dataset keeps them."""
    return (float(camera.fx), float(camera.fy), float(camera.cx) + PIXEL_CENTER_SHIFT,
            float(camera.cy) + PIXEL_CENTER_SHIFT)  # fmt: skip
