"""Fundamental matrix: Hartley-normalized 8-point algorithm inside adaptive RANSAC (Sampson distance)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.linalg import null_vector
from estimation.geometry.ransac import random_samples, required_iterations

MIN_CORRESPONDENCES = 8
HYPOTHESES_PER_BATCH = 64
"""Minimal-sample hypotheses solved together by one batched SVD."""
MAX_REFITS = 5
PREVERIFICATION_POINTS = 50
PREVERIFICATION_FRACTION = 0.5
"""A hypothesis is scored on all points only if its inlier ratio on PREVERIFICATION_POINTS random ones
reaches this fraction of the best full inlier ratio so far (a cheap T(d,d)-style test)."""


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
    mean = uv.mean(axis=0)
    spread = np.linalg.norm(uv - mean, axis=1).mean()
    s = np.sqrt(2.0) / max(spread, 1e-12)
    T = np.array([[s, 0.0, -s * mean[0]], [0.0, s, -s * mean[1]], [0.0, 0.0, 1.0]])
    return Normalization(points=(uv - mean) * s, T=T)


def _epipolar_rows(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Rows of A f = 0 from x2^T F x1 = 0, for points (..., 2): (..., 9)."""
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    one = np.ones_like(u1)
    return np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, one], axis=-1)


def _enforce_rank_two(F: np.ndarray) -> np.ndarray:
    """Closest rank-2 matrix in Frobenius norm: zero the smallest singular value (batched)."""
    U, S, Vt = np.linalg.svd(F)
    S[..., 2] = 0.0
    return U @ (S[..., :, None] * Vt)


def _eight_point_normalized(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """min ||A f|| s.t. ||f|| = 1 on (N, 2) normalized points (last right singular vector), then rank 2."""
    F = null_vector(_epipolar_rows(x1, x2)).reshape(3, 3)
    return _enforce_rank_two(F)


def _eight_point_minimal(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Batched minimal samples (B, 8, 2): f = null vector of A via eigh(A^T A) (faster than SVD), rank 2."""
    A = _epipolar_rows(x1, x2)
    f = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)[1][..., :, 0]
    return _enforce_rank_two(f.reshape(-1, 3, 3))


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


def sampson_distance(F: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """d = |x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2), in pixels.

    F may be batched (B, 3, 3); the result is then (B, N).
    """
    x1 = np.hstack([uv1, np.ones((len(uv1), 1))])
    x2 = np.hstack([uv2, np.ones((len(uv2), 1))])
    Fx1 = x1 @ np.swapaxes(F, -1, -2)       # (..., N, 3)
    Ftx2 = x2 @ F
    algebraic = (Fx1 * x2).sum(axis=-1)
    gradient_sq = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    return np.abs(algebraic) / np.sqrt(np.maximum(gradient_sq, 1e-300))


def ransac_fundamental(uv1: np.ndarray, uv2: np.ndarray, config: RansacConfig) -> FundamentalResult:
    """F maximizing #{Sampson distance < threshold_px}; adaptive N = log(1-p)/log(1-w^8); refit on inliers."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    num = len(uv1)
    if num < MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(
            f"a fundamental matrix needs at least {MIN_CORRESPONDENCES} correspondences, got {num}"
        )
    rng = np.random.default_rng(config.seed)
    n1, n2 = hartley_normalization(uv1), hartley_normalization(uv2)
    best_F, best_mask, best_count = None, np.zeros(num, bool), -1
    needed, iterations = config.max_iterations, 0
    while iterations < needed:
        samples = random_samples(rng, num, MIN_CORRESPONDENCES, HYPOTHESES_PER_BATCH)
        F = _denormalize(_eight_point_minimal(n1.points[samples], n2.points[samples]), n1.T, n2.T)
        iterations += HYPOTHESES_PER_BATCH
        # Pre-verification: only hypotheses doing well on a random subset are scored on every point.
        subset = rng.choice(num, size=min(num, PREVERIFICATION_POINTS), replace=False)
        subset_ratio = (sampson_distance(F, uv1[subset], uv2[subset]) < config.threshold_px).mean(axis=1)
        F = F[subset_ratio >= PREVERIFICATION_FRACTION * max(best_count, 0) / num]
        if len(F) == 0:
            continue
        masks = sampson_distance(F, uv1, uv2) < config.threshold_px
        counts = masks.sum(axis=1)
        best = int(np.argmax(counts))
        if counts[best] > best_count:
            best_F, best_mask, best_count = F[best], masks[best], int(counts[best])
            needed = required_iterations(best_count / num, MIN_CORRESPONDENCES, config.confidence,
                                         config.max_iterations)
    if best_count < MIN_CORRESPONDENCES:
        raise DegenerateConfigurationError(f"RANSAC found no fundamental matrix with {MIN_CORRESPONDENCES}+ "
                                           f"inliers among {num} correspondences")
    # Least-squares refit on the consensus set, kept while the consensus does not shrink.
    for _ in range(MAX_REFITS):
        F_refit = eight_point(uv1[best_mask], uv2[best_mask])
        mask = sampson_distance(F_refit, uv1, uv2) < config.threshold_px
        if mask.sum() < best_count:
            break
        converged = np.array_equal(mask, best_mask)
        best_F, best_mask, best_count = F_refit, mask, int(mask.sum())
        if converged:
            break
    distance = sampson_distance(best_F, uv1, uv2)
    return FundamentalResult(F=best_F, inlier_mask=distance < config.threshold_px, sampson_px=distance,
                             iterations=iterations)
