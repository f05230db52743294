"""Scene bounds of a dataset: a reconstruction's normalization, box and near/far from its sparse points, and
the unbounded scene around any box."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from neural.bounds import Bounds, SceneNormalization
from neural.data.dataset import Dataset
from neural.errors import DatasetError

#: Percentiles of the sparse points that bound a reconstruction's box (robust to stray points).
POINT_BOX_PERCENTILES = (2.0, 98.0)
#: The box is enlarged by this factor around its centre, then scaled to fit [-1, 1]^3.
POINT_BOX_PADDING = 1.2
#: Near/far are this factor outside the closest / farthest sparse point seen in front of any camera.
DEPTH_MARGIN = 0.8
#: An unbounded scene's far bound, in half-sides of its inner cube (contracted to 2 - 1/1000 of the cube).
UNBOUNDED_FAR_HALF_SIDES = 1000.0


def normalization_from_points(points: np.ndarray) -> tuple[SceneNormalization, np.ndarray, np.ndarray]:
    """Centre the robust box of the points at 0 and scale its padded half-extent to 1; box in scene frame."""
    low, high = np.percentile(points, POINT_BOX_PERCENTILES, axis=0)
    centre = 0.5 * (low + high)
    half_extent = 0.5 * (high - low).max() * POINT_BOX_PADDING
    if half_extent <= 0:
        raise DatasetError("the sparse points are all at one place; cannot bound the scene")
    normalization = SceneNormalization(centre=tuple(float(c) for c in centre), scale=float(1.0 / half_extent))
    box_low = normalization.points_to_scene(centre - POINT_BOX_PADDING * 0.5 * (high - low))
    box_high = normalization.points_to_scene(centre + POINT_BOX_PADDING * 0.5 * (high - low))
    return normalization, box_low, box_high


def near_far_from_points(poses: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """Near/far = margins around the closest/farthest point in front of any camera (along -z, OpenGL)."""
    distances = []
    for c2w in poses:
        relative = points - c2w[:3, 3]
        in_front = relative @ (-c2w[:3, 2]) > 0
        distances.append(np.linalg.norm(relative[in_front], axis=1))
    all_distances = np.concatenate(distances)
    if all_distances.size == 0:
        raise DatasetError("no sparse point lies in front of any camera; poses and points disagree")
    low, high = np.percentile(all_distances, [1.0, 99.0])
    return float(low * DEPTH_MARGIN), float(high / DEPTH_MARGIN)


def unbounded_scene(dataset: Dataset) -> Dataset:
    """The dataset with an unbounded scene: its box grown to hold every camera, far pushed out to
    UNBOUNDED_FAR_HALF_SIDES half-sides of that box's cube (content beyond the box lives in contracted space).
    """
    centres = dataset.poses[:, :3, 3].astype(np.float64)
    low = np.minimum(np.asarray(dataset.scene.scene_box_min), centres.min(axis=0))
    high = np.maximum(np.asarray(dataset.scene.scene_box_max), centres.max(axis=0))
    half_side = 0.5 * float((high - low).max())
    scene = Bounds(
        near=dataset.scene.near,
        far=max(UNBOUNDED_FAR_HALF_SIDES * half_side, 2.0 * dataset.scene.far),
        scene_box_min=tuple(low.tolist()),
        scene_box_max=tuple(high.tolist()),
        unbounded=True,
    )
    return replace(dataset, scene=scene)
