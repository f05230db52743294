"""`sfmnerf reconstruct` output: transforms.json, its images and sparse points, re-centred and scaled into the
normalized scene frame (recorded as `normalization`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from estimation.artefacts import PLY_NAME, SPARSE_DIR, TRANSFORMS_NAME
from estimation.errors import InputError
from estimation.io.export import read_colmap_points, read_ply_points
from neural.bounds import Bounds
from neural.data.bounds import near_far_from_points, normalization_from_points
from neural.data.dataset import SPLITS, Dataset
from neural.data.depths import load_depth_rays
from neural.data.files import check_rigid_pose, image_path, read_json, require
from neural.data.images import ImageLoading
from neural.errors import DatasetError
from neural.undistortion import camera_from_transforms, pinhole_target, resample_to, to_nerfstudio_intrinsics

#: A reconstruction without listed splits holds out every HOLDOUT_EVERY-th frame for validation (LLFF).
HOLDOUT_EVERY = 8


def sparse_points(root: Path) -> np.ndarray:
    """The reconstruction's sparse points from points.ply, else sparse/points3D.txt."""
    for candidate, reader in (
        (root / PLY_NAME, read_ply_points),
        (root / SPARSE_DIR / "points3D.txt", read_colmap_points),
    ):
        if candidate.is_file():
            try:
                points = reader(candidate)
            except InputError as error:
                raise DatasetError(str(error)) from None
            if len(points) < 4:
                raise DatasetError(f"{candidate}: {len(points)} points; need at least 4 to bound the scene")
            return points
    raise DatasetError(f"{root}: no points.ply or sparse/points3D.txt to bound the scene with")


def load_reconstruction(
    root: Path, loading: ImageLoading = ImageLoading(), within: Path | None = None
) -> Dataset:
    """transforms.json (fl_x, fl_y, cx, cy, w, h, frames[file_path, transform_matrix]) + images + points.

    Image files must lie inside `within` when given. Loaded smaller, the intrinsics scale with the image:
    f' = f W'/W, c' = c W'/W per axis (pixel centres at +0.5 map onto each other because the image edges do).
    Photos with distortion (k1 k2 p1 p2) or intrinsics of their own are resampled into one pinhole camera
    (neural.undistortion), so the dataset's K describes every image.
    """
    json_path = root / TRANSFORMS_NAME
    meta = read_json(json_path)
    frames = require(meta, "frames", json_path)
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{json_path}: 'frames' is empty")
    width, height = int(require(meta, "w", json_path)), int(require(meta, "h", json_path))
    loaded_width, loaded_height = loading.size_for(width, height)
    scale = (loaded_width / width, loaded_height / height)
    file_camera = camera_from_transforms(meta, width, height, scale, str(json_path))
    images, poses, names, photo_cameras = [], [], [], []
    for index, frame in enumerate(frames):
        where = f"{json_path} frames[{index}]"
        file_path = require(frame, "file_path", where)
        photo_cameras.append(camera_from_transforms({**meta, **frame}, width, height, scale, where))
        poses.append(check_rigid_pose(require(frame, "transform_matrix", where), f"{where} ({file_path})"))
        image, original_size = loading.load(image_path(root, file_path, where, within))
        if original_size != (width, height):
            raise DatasetError(
                f"{root / file_path}: image size {original_size[0]}x{original_size[1]} differs from "
                f"w x h = {width}x{height} in {json_path}"
            )
        images.append(image)
        names.append(str(file_path))
    original_poses = np.stack(poses)
    points = sparse_points(root)
    normalization, box_low, box_high = normalization_from_points(points)
    scene_poses = normalization.pose_to_scene(original_poses)
    near, far = near_far_from_points(scene_poses, normalization.points_to_scene(points))
    scene = Bounds(
        near=near, far=far, scene_box_min=tuple(box_low.tolist()), scene_box_max=tuple(box_high.tolist())
    )
    target = file_camera
    if file_camera.model != "pinhole" or any(camera != file_camera for camera in photo_cameras):
        target = pinhole_target(file_camera, photo_cameras, loaded_width, loaded_height, str(json_path))
        images = [resample_to(image, camera, target)
                  for image, camera in zip(images, photo_cameras, strict=True)]
    fx, fy, cx, cy = to_nerfstudio_intrinsics(target)
    depth_rays = load_depth_rays(
        root, names, scene_poses, normalization, (fx, fy, cx, cy), (loaded_width, loaded_height)
    )
    return Dataset(
        images=np.stack(images),
        poses=scene_poses.astype(np.float32),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        scene=scene,
        splits=reconstruction_splits(meta, names, json_path),
        image_names=names,
        source=root,
        white_background=loading.white_background,
        normalization=normalization,
        depth_rays=depth_rays,
    )


def reconstruction_splits(meta: dict[str, Any], names: list[str], where: Path) -> dict[str, np.ndarray]:
    """Splits from `train_filenames`/`val_filenames`/`test_filenames` if listed (nerfstudio), else a holdout.

    Without lists, the LLFF convention: frames 0, HOLDOUT_EVERY, 2 HOLDOUT_EVERY, ... are held out for
    validation (at least one, so every reconstruction of two or more frames is evaluated on views it never
    trained on).
    """
    listed = {split: meta.get(f"{split}_filenames") for split in SPLITS}
    if any(value is not None for value in listed.values()):
        index_of = {name: i for i, name in enumerate(names)}
        splits = {}
        for split, files in listed.items():
            if files is None:
                continue
            missing = [f for f in files if f not in index_of]
            if missing:
                raise DatasetError(f"{where}: {split}_filenames names {missing[0]!r}, which no frame has")
            splits[split] = np.array([index_of[f] for f in files], dtype=np.int64)
        return splits
    all_indices = np.arange(len(names))
    if len(names) < 2:
        raise DatasetError(f"{where}: one frame; a held-out view needs at least two")
    is_val = all_indices % HOLDOUT_EVERY == 0
    return {"train": all_indices[~is_val], "val": all_indices[is_val]}
