"""Essential matrix from F and K, its four pose candidates, and chirality disambiguation.

The first camera is the world frame (R = I, C = 0); candidates are the second camera's pose.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.errors import DegenerateConfigurationError
from estimation.geometry.triangulation import observations_for_pair, triangulate_linear
from estimation.types import CameraPose

W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


class RelativePose(NamedTuple):
    """Second camera's pose relative to the first (R = I, C = 0), with the linear points it implies."""

    pose: CameraPose
    points: np.ndarray          # (N, 3) linear triangulation under `pose`
    in_front: np.ndarray        # (N,) bool: r3 . (X - C) > 0 in both cameras
    candidate_scores: list[int]  # points in front of both cameras, per candidate


def essential_from_fundamental(F: np.ndarray, K: np.ndarray) -> np.ndarray:
    """E = K^T F K with its singular values projected to (1, 1, 0)."""
    U, _, Vt = np.linalg.svd(K.T @ F @ K)
    return U @ np.diag([1.0, 1.0, 0.0]) @ Vt


def pose_candidates(E: np.ndarray) -> list[CameraPose]:
    """The four (R, C) with E ~ [t]x R: R in {U W V^T, U W^T V^T}, t = +-u3, C = -R^T t (det R = +1)."""
    U, _, Vt = np.linalg.svd(E)
    candidates = []
    for R in (U @ W @ Vt, U @ W.T @ Vt):
        # E and -E describe the same geometry: flip to a proper rotation.
        R = R * np.sign(np.linalg.det(R))
        for t in (U[:, 2], -U[:, 2]):
            candidates.append(CameraPose(R=R, t=t.copy()))
    return candidates


def in_front_of_both(pose: CameraPose, points: np.ndarray) -> np.ndarray:
    """Chirality: r3 . (X - C) > 0 for the second camera and X_z > 0 for the first (R = I, C = 0)."""
    return (points[:, 2] > 0) & ((points - pose.center) @ pose.R[2] > 0)


def choose_relative_pose(E: np.ndarray, K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> RelativePose:
    """The candidate putting most linearly triangulated points in front of both cameras."""
    if len(uv1) < 1:
        raise DegenerateConfigurationError("no correspondences to disambiguate the relative pose with")
    best: RelativePose | None = None
    scores: list[int] = []
    for candidate in pose_candidates(E):
        obs = observations_for_pair(np.eye(3), np.zeros(3), candidate.R, candidate.t, uv1, uv2)
        points = triangulate_linear(K, obs).points
        in_front = in_front_of_both(candidate, points)
        scores.append(int(in_front.sum()))
        if best is None or scores[-1] > best.in_front.sum():
            best = RelativePose(pose=candidate, points=points, in_front=in_front, candidate_scores=[])
    return best._replace(candidate_scores=scores)
