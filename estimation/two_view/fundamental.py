"""Fundamental matrix: Hartley-normalized 8-point algorithm inside the RANSAC driver (Sampson distance)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.linalg import eigh, null_vector
from estimation.geometry.ransac import ransac

MIN_CORRESPONDENCES = 8
SQRT2 = np.sqrt(2.0)
"""The mean distance of Hartley-normalized points from their centroid."""


class Normalization(NamedTuple):
    """x_n = T x: centroid at the origin, mean distance sqrt(2) (Hartley)."""

    points: np.ndarray   # (N, 2) normalized
    T: np.ndarray        # (3, 3)


class FundamentalResult(NamedTuple):
    """x2^T F x1 = 0 for the inliers (pixel coordinates)."""

    F: np.ndarray                 # (3, 3), rank 2, ||F|| = 1
    inlier_mask: np.ndarray       # (N,) bool
    sampson_px: np.ndarray        # (N,) Sampson distance of every correspondence under F
    iterations: int


def hartley_normalization(uv: np.ndarray) -> Normalization:
    """T = [[s, 0, -s mx], [0, s, -s my], [0, 0, 1]] with s = sqrt(2) / mean ||uv - m||."""
    # Called on every LO re-fit: the centred points are formed once, their lengths summed directly and the
    # means taken as sums over N (np.linalg.norm's and ndarray.mean's dispatch cost more than the
    # arithmetic; the result is bitwise the same).
    mean = uv.sum(axis=0) / len(uv)
    centred = uv - mean
    spread = np.sqrt((centred * centred).sum(axis=1)).sum() / len(uv)
    s = SQRT2 / max(spread, 1e-12)
    T = np.array([[s, 0.0, -s * mean[0]], [0.0, s, -s * mean[1]], [0.0, 0.0, 1.0]])
    return Normalization(points=centred * s, T=T)


def epipolar_rows(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Rows (u2 u1, u2 v1, u2, v2 u1, v2 v1, v2, u1, v1, 1) of A f = 0 from x2^T F x1 = 0, for points
    (..., 2): (..., 9)."""
    # Written column by column into one array: half the cost of np.stack's nine temporaries and copy.
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    rows = np.empty((*x1.shape[:-1], 9))
    np.multiply(u2, u1, out=rows[..., 0])
    np.multiply(u2, v1, out=rows[..., 1])
    rows[..., 2] = u2
    np.multiply(v2, u1, out=rows[..., 3])
    np.multiply(v2, v1, out=rows[..., 4])
    rows[..., 5] = v2
    rows[..., 6:8] = x1
    rows[..., 8] = 1.0
    return rows


def _enforce_rank_two(F: np.ndarray) -> np.ndarray:
    """Closest rank-2 matrix in Frobenius norm: F (I - v v^T), v the right singular vector of F's smallest
    singular value, the eigenvector of F^T F's smallest eigenvalue (batched)."""
    # eigh of the 3 x 3 F^T F costs half the SVD of F (a batch of 64 minimal F: 65 vs 113 us).
    v = eigh(F.swapaxes(-1, -2) @ F)[1][..., 0]
    return F - (F @ v[..., None]) * v[..., None, :]


def _eight_point_normalized(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """min ||A f|| s.t. ||f|| = 1 on (N, 2) normalized points (last right singular vector), then rank 2."""
    F = null_vector(epipolar_rows(x1, x2)).reshape(3, 3)
    return _enforce_rank_two(F)


def _eight_point_minimal(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Batched minimal samples (B, 8, 2): f = the null vector of the 8 x 9 A (`null_vector`), rank 2."""
    return _enforce_rank_two(null_vector(epipolar_rows(x1, x2)).reshape(-1, 3, 3))


def _denormalize(F_n: np.ndarray, T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """F = T2^T F_n T1, scaled to unit Frobenius norm (batched)."""
    F = T2.T @ F_n @ T1
    return F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)


def eight_point(uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """Normalized 8-point: F = T2^T F_n T1 with F_n = argmin ||A f||, rank 2 by SVD (N >= 8 points)."""
    if len(uv1) < MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"the 8-point algorithm needs at least {MIN_CORRESPONDENCES} correspondences, got {len(uv1)}"
        )
    n1, n2 = hartley_normalization(uv1), hartley_normalization(uv2)
    return _denormalize(_eight_point_normalized(n1.points, n2.points), n1.T, n2.T)


def sampson_residual(F: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """r = x2^T F x1 / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2): signed, in pixels.

    F may be batched (B, 3, 3); the result is then (B, N).
    """
    # F x1 and F^T x2 of every model as one matrix product each (rows of all models stacked): a batched
    # matmul over tiny (3, 2) matrices costs twice as much. Sums and squares are taken in place (fewer
    # temporaries: ~10% less time on the ~270 models of a batch of 5-point samples, bitwise the same).
    models, num = F.shape[:-2], len(uv1)
    Fx1 = F[..., :2].reshape(-1, 2) @ uv1.T
    Fx1 += F[..., 2].reshape(-1, 1)
    Fx1 = Fx1.reshape(*models, 3, num)
    Ftx2 = F[..., :2, :2].swapaxes(-1, -2).reshape(-1, 2) @ uv2.T
    Ftx2 += F[..., 2, :2].reshape(-1, 1)
    Ftx2 = Ftx2.reshape(*models, 2, num)
    algebraic = Fx1[..., 0, :] * uv2[:, 0]
    algebraic += Fx1[..., 1, :] * uv2[:, 1]
    algebraic += Fx1[..., 2, :]
    Fx1 *= Fx1
    Ftx2 *= Ftx2
    gradient_sq = Fx1[..., 0, :] + Fx1[..., 1, :]
    gradient_sq += Ftx2[..., 0, :]
    gradient_sq += Ftx2[..., 1, :]
    algebraic /= np.sqrt(np.maximum(gradient_sq, 1e-300, out=gradient_sq), out=gradient_sq)
    return algebraic


def sampson_distance(F: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """d = |sampson_residual|: first-order distance of (x1, x2) to the epipolar variety, in pixels."""
    return np.abs(sampson_residual(F, uv1, uv2))


def ransac_fundamental(uv1: np.ndarray, uv2: np.ndarray, config: RansacConfig) -> FundamentalResult:
    """F maximizing #{Sampson distance < threshold_px}: minimal 8-point samples in the RANSAC driver,
    each new best F re-fitted by the normalized 8-point on its inliers (LO-RANSAC)."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    if len(uv1) < MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"a fundamental matrix needs at least {MIN_CORRESPONDENCES} correspondences, got {len(uv1)}"
        )
    # One normalization of all points serves every minimal sample.
    T1, T2 = hartley_normalization(uv1).T, hartley_normalization(uv2).T

    def minimal(sample1: np.ndarray, sample2: np.ndarray) -> np.ndarray:
        x1 = sample1 @ T1[:2, :2].T + T1[:2, 2]
        x2 = sample2 @ T2[:2, :2].T + T2[:2, 2]
        return _denormalize(_eight_point_minimal(x1, x2), T1, T2)

    result = ransac((uv1, uv2), minimal, MIN_CORRESPONDENCES, sampson_distance, config.threshold_px, config,
                    refit=lambda inliers1, inliers2: eight_point(inliers1, inliers2)[None],
                    model_name="fundamental matrix")
    return FundamentalResult(F=result.model, inlier_mask=result.inlier_mask, sampson_px=result.residuals,
                             iterations=result.iterations)
