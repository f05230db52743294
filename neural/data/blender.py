"""Blender folders (transforms_{train,val,test}.json + RGBA PNGs) and the NeRF-synthetic scene they share
with tiny-NeRF files."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from neural.bounds import Bounds
from neural.data.dataset import SPLITS, Dataset
from neural.data.files import check_rigid_pose, image_path, read_json, require
from neural.data.images import ImageLoading, check_same_size
from neural.errors import DatasetError

#: The NeRF-synthetic convention for Blender scenes and tiny-NeRF files without their own bounds.
SYNTHETIC_NEAR, SYNTHETIC_FAR = 2.0, 6.0
SYNTHETIC_BOX_HALF_SIZE = 1.5


def synthetic_dataset(
    images: np.ndarray,
    poses: np.ndarray,
    focal: float,
    near: float,
    far: float,
    splits: dict[str, np.ndarray],
    image_names: list[str],
    source: Path,
    white_background: bool = True,
    original_size: tuple[int, int] | None = None,
) -> Dataset:
    """A NeRF-synthetic scene: one pinhole focal, principal point at the image centre, the fixed scene box.

    focal is for images of original_size (width, height; default: as loaded), scaled to the loaded size.
    """
    height, width = images.shape[1:3]
    original_width, original_height = original_size or (width, height)
    half = SYNTHETIC_BOX_HALF_SIZE
    return Dataset(
        images=images,
        poses=poses.astype(np.float32),
        fx=focal * width / original_width,
        fy=focal * height / original_height,
        cx=width / 2.0,
        cy=height / 2.0,
        scene=Bounds(
            near=near, far=far, scene_box_min=(-half, -half, -half), scene_box_max=(half, half, half)
        ),
        splits=splits,
        image_names=image_names,
        source=source,
        white_background=white_background,
    )


def load_blender(root: Path, loading: ImageLoading = ImageLoading()) -> Dataset:
    """transforms_{split}.json (camera_angle_x or fl_x, frames[file_path, transform_matrix]) + RGBA PNGs."""
    images: list[np.ndarray] = []
    original_sizes: list[tuple[int, int]] = []
    poses: list[np.ndarray] = []
    names: list[str] = []
    splits: dict[str, np.ndarray] = {}
    focal: float | None = None
    near, far = SYNTHETIC_NEAR, SYNTHETIC_FAR
    for split in SPLITS:
        json_path = root / f"transforms_{split}.json"
        if not json_path.is_file():
            continue
        meta = read_json(json_path)
        frames = require(meta, "frames", json_path)
        if not isinstance(frames, list) or not frames:
            raise DatasetError(f"{json_path}: 'frames' is empty; the {split} split has no images")
        near, far = float(meta.get("near", near)), float(meta.get("far", far))
        start = len(images)
        for index, frame in enumerate(frames):
            where = f"{json_path} frames[{index}]"
            file_path = require(frame, "file_path", where)
            poses.append(
                check_rigid_pose(require(frame, "transform_matrix", where), f"{where} ({file_path})")
            )
            image, original_size = loading.load(image_path(root, file_path, where, within=root))
            images.append(image)
            original_sizes.append(original_size)
            names.append(str(file_path))
            check_same_size(images[-1], names[-1], images[0], names[0])
        splits[split] = np.arange(start, len(images))
        width = original_sizes[start][0]
        split_focal = focal_from_meta(meta, width, json_path)
        if focal is not None and not math.isclose(focal, split_focal, rel_tol=1e-4):
            raise DatasetError(
                f"{json_path}: focal {split_focal:.4f} differs from the other splits' {focal:.4f}"
            )
        focal = split_focal
    assert focal is not None
    return synthetic_dataset(
        np.stack(images), np.stack(poses), focal, near, far, splits, names, root, loading.white_background,
        original_sizes[0],
    )  # fmt: skip


def focal_from_meta(meta: dict[str, Any], width: int, where: Path) -> float:
    """fx = fl_x if given, else 0.5 W / tan(0.5 camera_angle_x)."""
    if "fl_x" in meta:
        return float(meta["fl_x"])
    if "camera_angle_x" not in meta:
        raise DatasetError(f"{where}: missing key 'camera_angle_x' (or 'fl_x')")
    return 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))
