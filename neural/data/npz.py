"""tiny-NeRF .npz files: images, poses, focal; optional split codes and near/far."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neural.data.blender import SYNTHETIC_FAR, SYNTHETIC_NEAR, synthetic_dataset
from neural.data.dataset import SPLITS, Dataset
from neural.data.files import check_rigid_pose
from neural.data.images import ImageLoading, resize_image
from neural.errors import DatasetError


def load_npz(path: Path, loading: ImageLoading = ImageLoading()) -> Dataset:
    """images (N,H,W,3) in [0,1], poses (N,4,4) c2w, focal; optional split (0/1/2: train/val/test), near/far.

    Without `split`, every tenth image (index % 10 == 9) is held out for validation. RGBA arrays are
    composited on white (the format's convention); `loading` may shrink the images (never cached: they are
    in memory already).
    """
    try:
        archive = np.load(path)
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read the .npz file ({error})") from None
    with archive:
        for key in ("images", "poses", "focal"):
            if key not in archive:
                raise DatasetError(f"{path}: missing array {key!r} (have {', '.join(archive.files)})")
        images = np.asarray(archive["images"], dtype=np.float32)
        poses = np.asarray(archive["poses"], dtype=np.float64)
        focal = float(np.asarray(archive["focal"]).reshape(-1)[0])
        split_codes = np.asarray(archive["split"]) if "split" in archive else None
        near = float(archive["near"]) if "near" in archive else SYNTHETIC_NEAR
        far = float(archive["far"]) if "far" in archive else SYNTHETIC_FAR
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise DatasetError(f"{path}: 'images' must be (N,H,W,3), got shape {images.shape}")
    if images.shape[-1] == 4:  # composite on white, the format's convention
        images = images[..., :3] * images[..., 3:] + (1.0 - images[..., 3:])
    if poses.shape[0] != images.shape[0]:
        raise DatasetError(f"{path}: {images.shape[0]} images but {poses.shape[0]} 'poses'")
    checked = np.stack([check_rigid_pose(pose, f"{path} poses[{i}]") for i, pose in enumerate(poses)])
    count = images.shape[0]
    if split_codes is None:
        is_val = np.arange(count) % 10 == 9
        split_codes = np.where(is_val, 1, 0)
    if split_codes.shape != (count,):
        raise DatasetError(
            f"{path}: 'split' must have one entry per image ({count}), got {split_codes.shape}"
        )
    splits = {name: np.flatnonzero(split_codes == code) for code, name in enumerate(SPLITS)}
    splits = {name: indices for name, indices in splits.items() if len(indices)}
    if "train" not in splits:
        raise DatasetError(f"{path}: 'split' has no training images (code 0)")
    names = [f"{path.stem}[{i}]" for i in range(count)]
    original_size = (images.shape[2], images.shape[1])
    width, height = loading.size_for(*original_size)
    images = np.stack([resize_image(image, width, height) for image in np.clip(images, 0.0, 1.0)])
    return synthetic_dataset(
        images, checked, focal, near, far, splits, names, path, original_size=original_size
    )
