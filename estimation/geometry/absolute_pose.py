"""Absolute camera pose from 2D-3D correspondences: minimal P3P inside LO-RANSAC, then non-linear refinement.

The minimal solver is OpenCV's P3P (Ding et al. 2023, up to four poses per sample); every solution is
scored. When a hypothesis beats the best consensus so far, the local optimization of LO-RANSAC
(Chum et al. 2003, as COLMAP's LORANSAC) refits EPnP on its inliers and keeps the refit if it gathers
more. The winner is refined by `pnp_nonlinear` (Levenberg-Marquardt on the reprojection error) on its
inliers. The seed's 6-point DLT (`pnp.pnp_ransac`) stays available as the linear alternative.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.pnp import pnp_nonlinear, projection_errors
from estimation.geometry.ransac import random_samples, required_iterations
from estimation.types import CameraPose

P3P_SAMPLE_SIZE = 3
EPNP_MIN_CORRESPONDENCES = 6
"""cv2's EPnP (and `pnp_nonlinear`) need this many correspondences."""
HYPOTHESES_PER_BATCH = 32
LOCAL_OPTIMIZATION_ROUNDS = 3
"""EPnP refits on the inliers of a new best hypothesis (LO-RANSAC), at most this many while they improve."""


class AbsolutePoseResult(NamedTuple):
    """World-to-camera pose refined on its inliers, the consensus and the effort."""

    pose: CameraPose
    inlier_mask: np.ndarray  # (N,) bool: reprojection error below the threshold under `pose`
    iterations: int  # minimal samples drawn
    local_optimizations: int  # EPnP refits that improved the consensus


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


def _inliers(
    K: np.ndarray, pose: CameraPose, points: np.ndarray, uv: np.ndarray, threshold: float
) -> np.ndarray:
    return projection_errors(K, np.concatenate([pose.R, pose.t[:, None]], axis=1), points, uv) < threshold


def absolute_pose_ransac(
    K: np.ndarray, points: np.ndarray, uv: np.ndarray, config: RansacConfig
) -> AbsolutePoseResult:
    """argmax_{R,t} #{||pi(K (R X + t)) - uv|| < pnp_threshold_px}: P3P samples, EPnP local optimization,
    N = log(1-p)/log(1-w^3) adaptive iterations; the winner refined by Levenberg-Marquardt on its inliers."""
    points, uv, K = np.asarray(points, float), np.asarray(uv, float), np.asarray(K, float)
    num = len(points)
    if num < EPNP_MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"absolute pose needs at least {EPNP_MIN_CORRESPONDENCES} 2D-3D correspondences, got {num}"
        )
    threshold = config.pnp_threshold_px
    rng = np.random.default_rng(config.seed)
    best_pose, best_mask, best_count = None, np.zeros(num, bool), 0
    needed, iterations, local_optimizations = config.max_iterations, 0, 0
    while iterations < needed:
        samples = random_samples(rng, num, P3P_SAMPLE_SIZE, HYPOTHESES_PER_BATCH)
        iterations += HYPOTHESES_PER_BATCH
        hypotheses = [pose for sample in samples for pose in p3p(K, points[sample], uv[sample])]
        if not hypotheses:
            continue
        P = np.stack([np.concatenate([pose.R, pose.t[:, None]], axis=1) for pose in hypotheses])
        masks = projection_errors(K, P, points, uv) < threshold
        counts = masks.sum(axis=1)
        best = int(np.argmax(counts))
        if counts[best] <= best_count:
            continue
        best_pose, best_mask, best_count = hypotheses[best], masks[best], int(counts[best])
        for _ in range(LOCAL_OPTIMIZATION_ROUNDS):
            if best_count < EPNP_MIN_CORRESPONDENCES:
                break
            refit = epnp(K, points[best_mask], uv[best_mask])
            if refit is None:
                break
            refit_mask = _inliers(K, refit, points, uv, threshold)
            if refit_mask.sum() <= best_count:
                break
            best_pose, best_mask, best_count = refit, refit_mask, int(refit_mask.sum())
            local_optimizations += 1
        needed = required_iterations(
            best_count / num, P3P_SAMPLE_SIZE, config.confidence, config.max_iterations
        )
    if best_pose is None or best_count < EPNP_MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"absolute pose RANSAC found no pose with {EPNP_MIN_CORRESPONDENCES}+ inliers among {num} "
            f"2D-3D correspondences"
        )
    refined = pnp_nonlinear(K, points[best_mask], uv[best_mask], best_pose).pose
    refined_mask = _inliers(K, refined, points, uv, threshold)
    if refined_mask.sum() < best_count:  # the refinement may not lose the consensus it started from
        refined, refined_mask = best_pose, best_mask
    return AbsolutePoseResult(
        pose=refined, inlier_mask=refined_mask, iterations=iterations, local_optimizations=local_optimizations
    )
