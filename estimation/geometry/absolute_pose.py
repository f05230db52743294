"""Absolute camera pose from 2D-3D correspondences: minimal P3P inside LO-RANSAC, then non-linear refinement.

The minimal solver is Grunert's P3P (1841; Haralick et al. 1994), solved for a whole batch of samples at
once: the quartic's roots as 4x4 companion-matrix eigenvalues, the distances polished by Gauss-Newton as
in Lambda Twist (Persson and Nordberg 2018), up to four poses per sample; every solution is
scored by the project's one RANSAC driver (`geometry.ransac`). When a hypothesis beats the best
consensus so far, the driver's local optimization (LO-RANSAC, Chum et al. 2003, as COLMAP's LORANSAC)
refits EPnP on its inliers and keeps the refit while the consensus does not shrink. The winner is
refined by `pnp.refine_pose` (Levenberg-Marquardt on the reprojection error) on its inliers. The seed's
6-point DLT (`pnp.pnp_ransac`) stays available as the linear alternative.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.pnp import refine_pose, reprojection_errors_per_hypothesis
from estimation.geometry.ransac import ransac
from estimation.types import CameraPose

P3P_SAMPLE_SIZE = 3
EPNP_MIN_CORRESPONDENCES = 6
"""cv2's EPnP (and `pnp.refine_pose`) need this many correspondences."""
ROOT_IMAGINARY_TOLERANCE = 1e-6
"""A root whose imaginary part is below this (relative) counts as real: a double root splits into a
near-real complex pair under rounding."""
PAIRS_23_13_12 = ((1, 2), (0, 2), (0, 1))
"""Point pairs of the sides a = |X2 - X3|, b = |X1 - X3|, c = |X1 - X2| (Grunert's naming)."""
DISTANCE_REFINEMENT_STEPS = 2
"""Gauss-Newton steps on the three distances: the quartic's roots lose digits where it is ill-conditioned
(true poses off by up to 5e-7 on 2000 random samples); two steps bring them within 1e-10."""
V_SQUARED_MINUS_ONE = np.array([-1.0, 0.0, 1.0])
CONSTANT_ONE = np.array([1.0, 0.0, 0.0])
"""Ascending coefficients of v^2 - 1 and of 1, as quadratics."""
LEADING_COEFFICIENT_FLOOR = 1e-14
"""Smallest |leading coefficient| of the normalized quartic (a root near infinity stays finite)."""


class AbsolutePoseResult(NamedTuple):
    """World-to-camera pose refined on its inliers, the consensus and the effort."""

    pose: CameraPose
    inlier_mask: np.ndarray  # (N,) bool: reprojection error below the threshold under `pose`
    iterations: int  # minimal samples drawn


def _pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """[R | t] (3, 4) from OpenCV's rotation vector and translation."""
    return np.concatenate([cv2.Rodrigues(rvec)[0], np.reshape(tvec, (3, 1))], axis=1)


class P3PSolutions(NamedTuple):
    """Every real pose with the three points in front of the camera, for a batch of samples."""

    poses: np.ndarray          # (M, 3, 4) world-to-camera [R | t]
    sample_index: np.ndarray   # (M,) the sample each pose solves


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for (B, 3) rows (np.cross's axis handling costs more than the product on small batches)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _poly_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(p q)(v) for batched ascending coefficients p (B, m), q (B, n) -> (B, m + n - 1)."""
    product = np.zeros((len(p), p.shape[1] + q.shape[1] - 1))
    for power, coefficient in enumerate(q.T):
        product[:, power : power + p.shape[1]] += p * coefficient[:, None]
    return product


def _poly_value(coefficients: np.ndarray, v: np.ndarray) -> np.ndarray:
    """sum_k c_k v^k for ascending coefficients (B, n) at v (B, r) -> (B, r) (Horner)."""
    value = np.zeros_like(v)
    for coefficient in coefficients.T[::-1]:
        value = value * v + coefficient[:, None]
    return value


class GrunertPolynomials(NamedTuple):
    """Grunert's quartic in v = s3 / s1 and the rational u(v) = s2 / s1 = N(v) / D(v)."""

    quartic: np.ndarray      # (B, 5) ascending coefficients
    numerator: np.ndarray    # (B, 3) N
    denominator: np.ndarray  # (B, 2) D


def grunert_polynomials(cos_23: np.ndarray, cos_13: np.ndarray, cos_12: np.ndarray, a2: np.ndarray,
                        b2: np.ndarray, c2: np.ndarray) -> GrunertPolynomials:
    """b^2 N^2 - 2 b^2 cos_12 N D + (b^2 - c^2 q) D^2 = 0 with q = 1 + v^2 - 2 v cos_13,
    N = b^2 (v^2 - 1) - (a^2 - c^2) q, D = 2 b^2 (cos_23 v - cos_12).

    From the law of cosines on distances s_k along unit rays j_k (cos_jk = j_j . j_k) to X_k with
    a = |X2 - X3|, b = |X1 - X3|, c = |X1 - X2|: u = N / D makes the a^2 and c^2 equations agree."""
    one = np.ones_like(a2)
    q = np.stack([one, -2 * cos_13, one], axis=1)
    numerator = b2[:, None] * V_SQUARED_MINUS_ONE - (a2 - c2)[:, None] * q
    denominator = 2 * b2[:, None] * np.stack([-cos_12, cos_23], axis=1)
    cubic = 2 * (b2 * cos_12)[:, None] * _poly_mul(numerator, denominator)       # degree 3 of 4
    quartic = (b2[:, None] * _poly_mul(numerator, numerator)
               - np.concatenate([cubic, np.zeros((len(cubic), 1))], axis=1)
               + _poly_mul(b2[:, None] * CONSTANT_ONE - c2[:, None] * q, _poly_mul(denominator, denominator)))
    return GrunertPolynomials(quartic=quartic, numerator=numerator, denominator=denominator)


def quartic_real_roots(quartic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of sum_k c_k v^k (ascending (B, 5)) as eigenvalues of the 4x4 companion matrix:
    (roots (B, 4), real (B, 4) bool)."""
    scale = np.max(np.abs(quartic), axis=1, keepdims=True)
    quartic = quartic / np.where(scale > 0, scale, 1.0)
    leading = quartic[:, 4]
    # A vanishing leading coefficient sends one root to infinity; keep it finite, it is filtered later.
    leading = np.where(np.abs(leading) < LEADING_COEFFICIENT_FLOOR,
                       np.where(leading < 0, -LEADING_COEFFICIENT_FLOOR, LEADING_COEFFICIENT_FLOOR), leading)
    companion = np.zeros((len(quartic), 4, 4))
    companion[:, 1:, :3] = np.eye(3)
    companion[:, :, 3] = -quartic[:, :4] / leading[:, None]
    roots = np.linalg.eigvals(companion)
    real = np.abs(roots.imag) <= ROOT_IMAGINARY_TOLERANCE * (1.0 + np.abs(roots.real))
    return roots.real, real & np.isfinite(roots.real)


def refine_distances(distances: np.ndarray, cosines: np.ndarray, squared_sides: np.ndarray) -> np.ndarray:
    """Gauss-Newton on f_jk = s_j^2 + s_k^2 - 2 s_j s_k cos_jk - d_jk^2 = 0, pairs jk = 12, 13, 23 (the
    law of cosines P3P solves; as Lambda Twist does): distances (M, 3) -> (M, 3)."""
    j, k = np.array([0, 0, 1]), np.array([1, 2, 2])
    for _ in range(DISTANCE_REFINEMENT_STEPS):
        s_j, s_k = distances[:, j], distances[:, k]
        f = s_j**2 + s_k**2 - 2 * s_j * s_k * cosines - squared_sides
        rows = np.zeros((3, len(distances), 3))                      # the Jacobian's rows df_jk / ds
        rows[[0, 1, 2], :, j] = 2 * (s_j - s_k * cosines).T
        rows[[0, 1, 2], :, k] = 2 * (s_k - s_j * cosines).T
        # J^-1 f = (f_0 r1 x r2 + f_1 r2 x r0 + f_2 r0 x r1) / det J (Cramer), skipped where J is singular.
        r1_x_r2 = _cross(rows[1], rows[2])
        adjugate_f = (f[:, 0:1] * r1_x_r2 + f[:, 1:2] * _cross(rows[2], rows[0])
                      + f[:, 2:3] * _cross(rows[0], rows[1]))
        determinant = np.einsum("bi,bi->b", rows[0], r1_x_r2)
        regular = determinant != 0.0
        distances = distances - np.where(regular[:, None], adjugate_f, 0.0) / np.where(
            regular, determinant, 1.0)[:, None]
    return distances


def rigid_from_triangles(world: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """[R | t] (B, 3, 4) with camera_k = R world_k + t for congruent triangles (B, 3, 3): R = F_c F_w^T
    for the orthonormal frames F = [e1, e3 x e1, e3] of edges e1 ~ X2 - X1, e3 ~ (X2 - X1) x (X3 - X1)."""

    # Both triangles' frames in one pass: (2B, 3, 3), the camera's first.
    triangles = np.concatenate([camera, world])
    e1 = triangles[:, 1] - triangles[:, 0]
    e3 = _cross(e1, triangles[:, 2] - triangles[:, 0])
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e3 /= np.linalg.norm(e3, axis=1, keepdims=True)
    frames = np.stack([e1, _cross(e3, e1), e3], axis=2)
    R = frames[: len(camera)] @ np.swapaxes(frames[len(camera):], 1, 2)
    t = camera.mean(axis=1) - np.einsum("bij,bj->bi", R, world.mean(axis=1))
    return np.concatenate([R, t[:, :, None]], axis=2)


def p3p_batch(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> P3PSolutions:
    """All poses with uv_k ~ K (R X_k + t), k = 1..3, of each sample (points (B, 3, 3), uv (B, 3, 2)):
    Grunert's quartic (`grunert_polynomials`) for the distances s_k, then R, t from the two triangles."""
    points, uv = np.asarray(points, float), np.asarray(uv, float)
    rays = np.concatenate([uv, np.ones(uv.shape[:2] + (1,))], axis=2) @ np.linalg.inv(K).T
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    cos_23, cos_13, cos_12 = (np.einsum("bi,bi->b", rays[:, j], rays[:, k]) for j, k in PAIRS_23_13_12)
    a2, b2, c2 = (np.sum((points[:, j] - points[:, k]) ** 2, axis=1) for j, k in PAIRS_23_13_12)
    # A sample repeating a point (SIFT puts several orientations on one keypoint) has no finite solution.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        polynomials = grunert_polynomials(cos_23, cos_13, cos_12, a2, b2, c2)
        v, real = quartic_real_roots(polynomials.quartic)
        u = _poly_value(polynomials.numerator, v) / _poly_value(polynomials.denominator, v)
        s1 = np.sqrt(b2[:, None] / (1.0 + v**2 - 2 * v * cos_13[:, None]))
        distances = np.stack([s1, u * s1, v * s1], axis=2)                     # (B, 4, 3)
        solution = np.flatnonzero(real & np.all(np.isfinite(distances) & (distances > 0), axis=2))
        sample_index = solution // 4                                           # 4 roots per sample
        # Rows by take (numpy 2's fancy row indexing of 2-D and 3-D arrays costs several times more).
        distances = refine_distances(distances.reshape(-1, 3).take(solution, axis=0),
                                     np.stack([cos_12, cos_13, cos_23], axis=1).take(sample_index, axis=0),
                                     np.stack([c2, b2, a2], axis=1).take(sample_index, axis=0))
        poses = rigid_from_triangles(points.take(sample_index, axis=0),
                                     distances[:, :, None] * rays.take(sample_index, axis=0))
    finite = np.all(np.isfinite(poses), axis=(1, 2)) & np.all(distances > 0, axis=1)
    return P3PSolutions(poses=poses.compress(finite, axis=0), sample_index=sample_index[finite])


def p3p(K: np.ndarray, points: np.ndarray, uv: np.ndarray) -> list[CameraPose]:
    """All poses with uv_k ~ K (R X_k + t) for exactly three correspondences (up to four, `p3p_batch`)."""
    if len(points) != P3P_SAMPLE_SIZE:
        raise DegenerateConfigurationError(f"P3P takes exactly 3 correspondences, got {len(points)}")
    poses = p3p_batch(K, np.asarray(points, float)[None], np.asarray(uv, float)[None]).poses
    return [CameraPose(R=P[:, :3], t=P[:, 3]) for P in poses]


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

    def minimal(sample_points: np.ndarray, sample_uv: np.ndarray) -> np.ndarray:
        return p3p_batch(K, sample_points, sample_uv).poses

    def residuals(P: np.ndarray, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        return reprojection_errors_per_hypothesis(K, P, X, x)

    def refit(X: np.ndarray, x: np.ndarray) -> np.ndarray:
        pose = epnp(K, X, x) if len(X) >= EPNP_MIN_CORRESPONDENCES else None
        if pose is None:
            return np.zeros((0, 3, 4))
        return np.concatenate([pose.R, pose.t[:, None]], axis=1)[None]

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
    refined = refine_pose(K, points[best_mask], uv[best_mask], best_pose)
    refined_mask = reprojection_errors_per_hypothesis(K, np.column_stack([refined.R, refined.t]), points,
                                                      uv) < threshold
    if refined_mask.sum() < best_mask.sum():  # the refinement may not lose the consensus it started from
        refined, refined_mask = best_pose, best_mask
    return AbsolutePoseResult(pose=refined, inlier_mask=refined_mask, iterations=result.iterations)
