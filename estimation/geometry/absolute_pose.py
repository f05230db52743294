"""Absolute camera pose from 2D-3D correspondences: minimal P3P inside LO-RANSAC, then non-linear refinement.

The minimal solver is OpenCV's P3P (Ding et al. 2023, up to four poses per sample); every solution is
scored by the project's one RANSAC driver (`geometry.ransac`). When a hypothesis beats the best
consensus so far, the driver's local optimization (LO-RANSAC, Chum et al. 2003, as COLMAP's LORANSAC)
refits EPnP on its inliers and keeps the refit while the consensus does not shrink. The winner is
refined by `pnp_nonlinear` (Levenberg-Marquardt on the reprojection error) on its inliers. The seed's
6-point DLT (`pnp.pnp_ransac`) stays available as the linear alternative.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.pnp import pnp_nonlinear, projection_errors
from estimation.geometry.ransac import ransac
from estimation.types import CameraPose

P3P_SAMPLE_SIZE = 3
EPNP_MIN_CORRESPONDENCES = 6
"""cv2's EPnP (and `pnp_nonlinear`) need this many correspondences."""


class AbsolutePoseResult(NamedTuple):
    """World-to-camera pose refined on its inliers, the consensus and the effort."""

    pose: CameraPose
    inlier_mask: np.ndarray  # (N,) bool: reprojection error below the threshold under `pose`
    iterations: int  # minimal samples drawn


def _pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """[R | t] (3, 4) from OpenCV's rotation vector and translation."""
    return np.concatenate([cv2.Rodrigues(rvec)[0], np.reshape(tvec, (3, 1))], axis=1)


def p3p(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> list[CameraPose]:
    """All poses with uv_k ~ K (R X_k + t) for exactly three correspondences (up to four, OpenCV P3P)."""
    if len(points) != P3P_SAMPLE_SIZE:
        raise DegenerateConfigurationError(f"P3P takes exactly 3 correspondences, got {len(points)}")
    _, rvecs, tvecs = cv2.solveP3P(
        np.ascontiguousarray(points, np.float64),
        np.ascontiguousarray(uv, np.float64),
        K,
        None,
        flags=cv2.SOLVEPNP_P3P,
    )
    poses = []
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        P = _pose_matrix(rvec, tvec)
        poses.append(CameraPose(R=P[:, :3], t=P[:, 3]))
    return poses


def epnp(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> CameraPose | None:
    """EPnP (Lepetit et al. 2009) on 6+ correspondences: x ~ K [R | t] X via four control points; None
    when OpenCV finds no solution."""
    ok, rvec, tvec = cv2.solvePnP(
        np.ascontiguousarray(points, np.float64),
        np.ascontiguousarray(uv, np.float64),
        K,
        None,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    P = _pose_matrix(rvec, tvec)
    return CameraPose(R=P[:, :3], t=P[:, 3])


def absolute_pose_ransac(
    K: np.ndarray, points: np.ndarray, uv: np.ndarray, config: RansacConfig
) -> AbsolutePoseResult:
    """argmax_{R,t} #{||pi(K (R X + t)) - uv|| < pnp_threshold_px}: P3P samples in the shared RANSAC driver
    (adaptive N = log(1-p)/log(1-w^3)), EPnP refits of each new best (LO-RANSAC), then Levenberg-Marquardt
    on the inliers."""
    points, uv, K = np.asarray(points, float), np.asarray(uv, float), np.asarray(K, float)
    if len(points) < EPNP_MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"absolute pose needs {EPNP_MIN_CORRESPONDENCES}+ 2D-3D correspondences, got {len(points)}"
        )
    threshold = config.pnp_threshold_px

    def as_matrices(poses: list[CameraPose]) -> np.ndarray:
        return np.array([np.concatenate([pose.R, pose.t[:, None]], axis=1) for pose in poses]).reshape(
            -1, 3, 4
        )

    def minimal(sample_points: np.ndarray, sample_uv: np.ndarray) -> np.ndarray:
        return as_matrices(
            [pose for X, x in zip(sample_points, sample_uv, strict=True) for pose in p3p(K, X, x)]
        )

    def residuals(P: np.ndarray, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        return projection_errors(K, P, X, x)

    def refit(X: np.ndarray, x: np.ndarray) -> np.ndarray:
        pose = epnp(K, X, x) if len(X) >= EPNP_MIN_CORRESPONDENCES else None
        return as_matrices([] if pose is None else [pose])

    result = ransac(
        (points, uv),
        minimal,
        P3P_SAMPLE_SIZE,
        residuals,
        threshold,
        config,
        refit=refit,
        model_name="camera pose",
    )
    best_pose = CameraPose(R=result.model[:, :3], t=result.model[:, 3])
    best_mask = result.inlier_mask
    if best_mask.sum() < EPNP_MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"absolute pose RANSAC found no pose with {EPNP_MIN_CORRESPONDENCES}+ inliers in {len(points)} "
            "2D-3D correspondences"
        )
    refined = pnp_nonlinear(K, points[best_mask], uv[best_mask], best_pose).pose
    refined_mask = (
        projection_errors(K, np.concatenate([refined.R, refined.t[:, None]], axis=1), points, uv) < threshold
    )
    if refined_mask.sum() < best_mask.sum():  # the refinement may not lose the consensus it started from
        refined, refined_mask = best_pose, best_mask
    return AbsolutePoseResult(pose=refined, inlier_mask=refined_mask, iterations=result.iterations)
