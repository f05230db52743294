"""Small readers and checks shared by the dataset loaders: JSON, keys, rigid poses, confined paths."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from neural.errors import DatasetError

#: Largest deviation of R^T R from I (and of det R from 1) accepted for a rigid pose.
RIGID_TOLERANCE = 1e-3


def check_rigid_pose(c2w: np.ndarray, where: str) -> np.ndarray:
    """c2w must be [[R, t], [0, 0, 0, 1]] with R^T R = I and det R = 1; returns it as float64 (4,4)."""
    try:
        matrix = np.asarray(c2w, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{where}: transform_matrix is not numeric ({error})") from None
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise DatasetError(f"{where}: transform_matrix must be 4x4, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{where}: transform_matrix has non-finite entries")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise DatasetError(
            f"{where}: transform_matrix last row must be [0, 0, 0, 1], got {matrix[3].tolist()}"
        )
    rotation = matrix[:3, :3]
    orthogonality = np.abs(rotation.T @ rotation - np.eye(3)).max()
    determinant = np.linalg.det(rotation)
    if orthogonality > RIGID_TOLERANCE or abs(determinant - 1.0) > RIGID_TOLERANCE:
        raise DatasetError(
            f"{where}: transform_matrix is not a rigid transform "
            f"(|R^T R - I| = {orthogonality:.3g}, det R = {determinant:.4g})"
        )
    return matrix


def read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise DatasetError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def require(data: dict[str, Any], key: str, where: Path | str) -> Any:
    if key not in data:
        raise DatasetError(f"{where}: missing key {key!r}")
    return data[key]


def confined_path(root: Path, file_path: Any, where: str, within: Path | None) -> Path:
    """root / file_path resolved (links followed); DatasetError naming `where` if it leaves `within`.

    The message is the same whether the target exists or not, so a dataset cannot probe the file system.
    `within` None: no bound (a local reconstruction's images may live anywhere).
    """
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{where}: file_path must be a non-empty string")
    candidate = (root / file_path).resolve()
    if within is not None and not candidate.is_relative_to(within.resolve()):
        raise DatasetError(f"{where}: file_path {file_path!r} points outside the dataset folder; refused")
    return candidate


def image_path(root: Path, file_path: str, where: str, within: Path | None) -> Path:
    """A frame's file_path relative to root, bounded by `within`; Blender's have no extension (then .png)."""
    candidate = confined_path(root, file_path, where, within)
    if candidate.suffix.lower() in (".png", ".jpg", ".jpeg") or candidate.is_file():
        return candidate
    return confined_path(root, f"{file_path}.png", where, within)
