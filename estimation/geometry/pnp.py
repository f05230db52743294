"""Camera pose from 2D-3D correspondences: linear DLT PnP inside RANSAC, then non-linear refinement."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.alignment import rotation_angle_deg
from estimation.geometry.linalg import null_vector
from estimation.geometry.projection import as_camera, project
from estimation.geometry.ransac import msac_cost, ransac
from estimation.types import CameraPose

MIN_CORRESPONDENCES = 6
TURN_AXES = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
"""Camera axes a pose is turned about for `consensus_from_turned_starts`: the image's horizontal and
vertical, both ways (a shallow patch leaves the rotation loosest about the axes in the image plane)."""
WIDE_REFITS, REFITS = 1, 1
"""Re-fits of each turned start on its inliers at twice the threshold, then at the threshold: the start's
inliers at the threshold alone are too few to pull it into its basin."""
SAME_BASIN_DEG = 1.0
"""A turned start that comes back within this of the pose is in the pose's own basin: it is not followed
further (what it could gain there is a borderline inlier, which the MSAC margin would refuse anyway)."""


class PnPResult(NamedTuple):
    """RANSAC consensus of the DLT projection, and the pose of the DLT refit on it (R by SVD)."""

    pose: CameraPose
    inlier_mask: np.ndarray       # (N,) bool
    iterations: int


class PnPConsensus(NamedTuple):
    """A pose and its inliers among the 2D-3D correspondences."""

    pose: CameraPose
    inlier_mask: np.ndarray       # (N,) bool


class PnPRefinement(NamedTuple):
    """Pose minimizing the reprojection error, with the RMS before and after (pixels)."""

    pose: CameraPose
    initial_rms_px: float
    final_rms_px: float


def _require(num: int) -> None:
    if num < MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"PnP needs at least {MIN_CORRESPONDENCES} 2D-3D correspondences, got {num}"
        )


def _point_normalization(points: np.ndarray) -> np.ndarray:
    """T (4x4) with T X = [s (X - m), 1]: centroid at the origin, mean distance sqrt(3)."""
    mean = points.mean(axis=0)
    s = np.sqrt(3.0) / max(np.linalg.norm(points - mean, axis=1).mean(), 1e-12)
    T = np.diag([s, s, s, 1.0])
    T[:3, 3] = -s * mean
    return T


def _dlt_projection(x: np.ndarray, X_h: np.ndarray) -> np.ndarray:
    """P (..., 3, 4) = argmin ||A p||, ||p|| = 1, rows of x ~ P X; x (..., N, 2) normalized, X (..., N, 4)."""
    zeros = np.zeros_like(X_h)
    row_u = np.concatenate([X_h, zeros, -x[..., 0:1] * X_h], axis=-1)
    row_v = np.concatenate([zeros, X_h, -x[..., 1:2] * X_h], axis=-1)
    A = np.concatenate([row_u, row_v], axis=-2)
    return null_vector(A).reshape(*A.shape[:-2], 3, 4)


def _fix_sign(P: np.ndarray) -> np.ndarray:
    """P ~ lambda [R | t] is defined up to sign; choose lambda > 0 (det M > 0) so depths are positive."""
    return P * np.sign(np.linalg.det(P[..., :3]))[..., None, None]


def _pose_from_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[R | t] from P = lambda [R | t], lambda > 0: R = U V^T from M = U D V^T, t = p4 / mean(D)."""
    U, D, Vt = np.linalg.svd(P[..., :3])
    return U @ Vt, P[..., 3] / D.mean(axis=-1)[..., None]


def _linear_pnp_batch(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Batched DLT on K^-1-normalized pixels: points (..., N, 3), uv (..., N, 2) -> P (..., 3, 4)."""
    T = _point_normalization(points.reshape(-1, 3))
    X_h = np.concatenate([points, np.ones((*points.shape[:-1], 1))], axis=-1) @ T.T
    x = (np.concatenate([uv, np.ones((*uv.shape[:-1], 1))], axis=-1) @ np.linalg.inv(K).T)[..., :2]
    return _fix_sign(_dlt_projection(x, X_h) @ T)


def pnp_linear(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> CameraPose:
    """DLT: x_n ~ [R | t] X on x_n = K^-1 [u v 1], 6+ points; R orthonormalized by SVD (R = U V^T)."""
    _require(len(points))
    R, t = _pose_from_projection(_linear_pnp_batch(K, np.asarray(points, float), np.asarray(uv, float)))
    return CameraPose(R=R, t=t)


def reprojection_errors_per_hypothesis(K: np.ndarray, P: np.ndarray, points: np.ndarray, uv: np.ndarray
                                       ) -> np.ndarray:
    """||pi(K P [X; 1]) - uv|| per hypothesis and point (pixels), inf behind the camera; P (..., 3, 4) ->
    (..., N): `projection.reprojection_errors` of many poses [R | t] (or DLT projections) at once, as the
    RANSAC scoring needs them.

    K P is formed first, and the rows of every hypothesis' K P multiply the points in one matrix product
    (a batched product of 3x3 blocks cost twice as much); K's last row is [0 0 1]: the third coordinate
    is the depth. The norm is sqrt(du^2 + dv^2) over both axes at once (np.hypot cost twice as much)."""
    KP = K @ P
    rows = KP.reshape(-1, 4)
    homogeneous = (rows[:, :3] @ points.T + rows[:, 3:]).reshape(-1, 3, len(points))   # (H, 3, N)
    in_front = homogeneous[:, 2:] > 0
    residuals = homogeneous[:, :2] / np.where(in_front, homogeneous[:, 2:], 1.0) - uv.T  # (H, 2, N)
    error = np.sqrt(np.einsum("hin,hin->hn", residuals, residuals))
    return np.where(in_front[:, 0], error, np.inf).reshape(*KP.shape[:-2], len(points))


def pnp_ransac(K: np.ndarray, points: np.ndarray, uv: np.ndarray, config: RansacConfig) -> PnPResult:
    """DLT maximizing #{reprojection < pnp_threshold_px}: 6-point DLT samples in the shared RANSAC driver
    (N = log(1-p)/log(1-w^6)), DLT refits on each new best's inliers (LO), then R by SVD.

    Hypotheses are scored with the DLT's own projection P (before orthonormalization, which is only
    accurate to about a degree with noisy, shallow structure); the pose is then P's nearest [R | t],
    meant as the start of `pnp_nonlinear`.
    """
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    _require(len(points))

    def minimal(sample_points: np.ndarray, sample_uv: np.ndarray) -> np.ndarray:
        return _linear_pnp_batch(K, sample_points, sample_uv)

    def residuals(P: np.ndarray, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        return reprojection_errors_per_hypothesis(K, P, X, x)

    def refit(X: np.ndarray, x: np.ndarray) -> np.ndarray:
        return _linear_pnp_batch(K, X, x)[None]

    result = ransac((points, uv), minimal, MIN_CORRESPONDENCES, residuals, config.pnp_threshold_px, config,
                    refit=refit, model_name="camera pose")
    R, t = _pose_from_projection(result.model)
    return PnPResult(pose=CameraPose(R=R, t=t), inlier_mask=result.inlier_mask, iterations=result.iterations)


def refine_pose(K: np.ndarray, points: np.ndarray, uv: np.ndarray, initial: CameraPose) -> CameraPose:
    """min_{R, t} sum ||pi(K (R X + t)) - uv||^2 from `initial`: OpenCV's Levenberg-Marquardt
    (solvePnPRefineLM, analytic Jacobian over a rotation vector)."""
    _require(len(points))
    points, uv = np.ascontiguousarray(points, np.float64), np.ascontiguousarray(uv, np.float64)
    rvec, tvec = cv2.solvePnPRefineLM(points, uv, np.asarray(K, np.float64), None,
                                      cv2.Rodrigues(initial.R)[0], np.reshape(initial.t, (3, 1)).copy())
    return CameraPose(R=cv2.Rodrigues(rvec)[0], t=tvec.ravel())


def pnp_nonlinear(K: np.ndarray, points: np.ndarray, uv: np.ndarray, initial: CameraPose) -> PnPRefinement:
    """`refine_pose`, with the RMS reprojection error before and after."""
    pose = refine_pose(K, points, uv, initial)

    def rms(start: CameraPose) -> float:
        residuals = project(as_camera(K), start.R, start.t, points).uv - uv
        return float(np.sqrt(np.mean(residuals**2) * 2))

    return PnPRefinement(pose=pose, initial_rms_px=rms(initial), final_rms_px=rms(pose))


def consensus_from_turned_starts(K: np.ndarray, points: np.ndarray, uv: np.ndarray, pose: CameraPose,
                                 threshold_px: float, turn_deg: float, min_gain: float) -> PnPConsensus:
    """The best of `pose` and `refine_pose` started from it turned by turn_deg about each of TURN_AXES around
    its inliers' centroid (R' = R_turn R, the centroid's camera coordinates kept), each re-fitted on its
    inliers (reprojection error e_i < threshold_px): a turned start replaces `pose` only with over
    (1 + min_gain) times its inliers at under (1 - min_gain) times its MSAC cost sum_i min(e_i^2,
    threshold_px^2) (turn_deg 0: `pose` as it is).

    The reprojection error of a pose from a narrow, shallow patch of points can have basins a few degrees
    apart that explain about as many correspondences; RANSAC's consensus may sit in the lesser one. A start
    that gains inliers only by fitting them more loosely is no better (lego, seed 10: 20 inliers instead
    of 19, 5.4 deg away, at a higher cost), and one that gains a borderline inlier or two at about the same
    cost is the same basin or a coin toss (lego_ring_400: 2.5 % lower or less, and its mean error rose)."""
    def errors(candidate: CameraPose) -> np.ndarray:
        return reprojection_errors_per_hypothesis(K, np.column_stack([candidate.R, candidate.t]), points, uv)

    def cost(candidate_errors: np.ndarray) -> float:
        return float(msac_cost(candidate_errors, threshold_px))

    pose_errors = errors(pose)
    best, best_cost = PnPConsensus(pose, pose_errors < threshold_px), cost(pose_errors)
    if turn_deg <= 0 or best.inlier_mask.sum() < MIN_CORRESPONDENCES:
        return best
    centroid = points[best.inlier_mask].mean(axis=0)
    needed = (1.0 + min_gain) * best.inlier_mask.sum()
    for axis in TURN_AXES:
        R = cv2.Rodrigues(np.radians(turn_deg) * axis)[0] @ pose.R
        candidate = CameraPose(R=R, t=pose.R @ centroid + pose.t - R @ centroid)
        for refit in range(WIDE_REFITS + REFITS):
            mask = errors(candidate) < threshold_px * (2.0 if refit < WIDE_REFITS else 1.0)
            if mask.sum() < MIN_CORRESPONDENCES:
                break
            candidate = refine_pose(K, points[mask], uv[mask], candidate)
            if rotation_angle_deg(candidate.R, pose.R) < SAME_BASIN_DEG:
                break
        else:
            candidate_errors = errors(candidate)
            mask, candidate_cost = candidate_errors < threshold_px, cost(candidate_errors)
            gains = mask.sum() > max(needed, best.inlier_mask.sum())
            if gains and candidate_cost < (1.0 - min_gain) * best_cost:
                best, best_cost = PnPConsensus(candidate, mask), candidate_cost
    return best
