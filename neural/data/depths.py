"""Depth supervision from a reconstruction: each observed sparse point as a known termination distance along
the ray through its pixel, with that distance's std-dev (the reconstruction's depths.npz, see
`estimation.io.export.DEPTH_FIELDS`), in the dataset's scene frame and pinhole camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimation.artefacts import DEPTHS_NAME
from estimation.errors import InputError
from estimation.io.export import read_depths
from neural.bounds import SceneNormalization
from neural.data.dataset import DepthRays
from neural.errors import DatasetError


def project_to_pixels(
    points: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, z): u = cx + fx x / z - 1/2, v = cy - fy y / z - 1/2, z = -z_cam, (x, y, z_cam) the point in
    its camera's OpenGL axes; (u, v) in `neural.rays`' pixel indices (pixel (u, v) centred at u + 1/2);
    points (O,3), c2w (O,4,4)."""
    local = np.einsum("oji,oj->oi", c2w[:, :3, :3], points - c2w[:, :3, 3])   # R^T (X - C)
    z = -local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cx + fx * local[:, 0] / z - 0.5
        v = cy - fy * local[:, 1] / z - 0.5
    return u, v, z


def load_depth_rays(
    root: Path,
    file_paths: list[str],
    poses: np.ndarray,
    normalization: SceneNormalization,
    intrinsics: tuple[float, float, float, float],
    size: tuple[int, int],
) -> DepthRays | None:
    """The depth rays of root/depths.npz (None when there is none) for frames `file_paths` (as listed in
    transforms.json) with scene-frame poses (N,4,4), pinhole (fx, fy, cx, cy) and image (width, height).

    Each point is re-projected into the dataset's pinhole camera (so undistortion and resizing apply to it
    as to the images); observations behind the camera or outside the image are dropped. distance = ||X - C||
    and sigma scale into the scene frame. DatasetError naming the file when its frames are not these.
    """
    path = root / DEPTHS_NAME
    if not path.is_file():
        return None
    try:
        depths = read_depths(path)
    except InputError as error:
        raise DatasetError(str(error)) from None
    if len(depths.file_paths) != len(file_paths):
        raise DatasetError(
            f"{path}: field 'file_paths' lists {len(depths.file_paths)} frames, transforms.json "
            f"{len(file_paths)}; the depths are of another reconstruction"
        )
    for index, (listed, frame) in enumerate(zip(depths.file_paths, file_paths, strict=True)):
        if listed != frame:
            raise DatasetError(
                f"{path}: field 'file_paths'[{index}] is {listed!r} but transforms.json frame {index} is "
                f"{frame!r}; the depths are of another reconstruction"
            )
    points = normalization.points_to_scene(depths.point)
    c2w = np.asarray(poses, np.float64)[depths.frame]
    u, v, z = project_to_pixels(points, c2w, *intrinsics)
    width, height = size
    seen = (z > 0) & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    return DepthRays(
        image=depths.frame[seen],
        u=u[seen],
        v=v[seen],
        distance=np.linalg.norm(points[seen] - c2w[seen, :3, 3], axis=1),
        sigma=depths.sigma[seen] * normalization.scale,
    )
