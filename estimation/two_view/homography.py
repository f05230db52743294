"""Homography x2 ~ H x1: normalized 4-point DLT inside the RANSAC driver (transfer error), and how far
H is from a pure rotation."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.config import RansacConfig
from estimation.geometry.linalg import inv, null_vector
from estimation.geometry.ransac import ransac
from estimation.two_view.fundamental import hartley_normalization

MIN_CORRESPONDENCES = 4


class HomographyResult(NamedTuple):
    """x2 ~ H x1 for the inliers (pixel coordinates)."""

    H: np.ndarray                 # (3, 3), unit Frobenius norm
    inlier_mask: np.ndarray       # (N,) bool
    transfer_px: np.ndarray       # (N,) ||pi(H x1) - x2|| of every correspondence
    iterations: int


def _homography_rows(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Rows of A h = 0 from x2 x (H x1) = 0 for points (..., N, 2): (..., 2N, 9), the N rows
    (0, -x1~, v2 x1~) then the N rows (x1~, 0, -u2 x1~), x1~ = (u1, v1, 1)."""
    # Written block by block into one array: a third less than concatenating the blocks (one copy each).
    num = x1.shape[-2]
    rows = np.zeros((*x1.shape[:-2], 2 * num, 9))
    row_u, row_v = rows[..., :num, :], rows[..., num:, :]
    np.negative(x1, out=row_u[..., 3:5])
    row_u[..., 5] = -1.0
    np.multiply(x2[..., 1:2], x1, out=row_u[..., 6:8])
    row_u[..., 8] = x2[..., 1]
    row_v[..., 0:2] = x1
    row_v[..., 2] = 1.0
    np.multiply(-x2[..., 0:1], x1, out=row_v[..., 6:8])
    row_v[..., 8] = -x2[..., 0]
    return rows


def _dlt(x1: np.ndarray, x2: np.ndarray, T1: np.ndarray, T2: np.ndarray, T2_inverse: np.ndarray
         ) -> np.ndarray:
    """H = T2^-1 H_n T1 with H_n = argmin ||A h||, ||h|| = 1 on points normalized by T1, T2 (batched)."""
    n1 = x1 @ T1[:2, :2].T + T1[:2, 2]
    n2 = x2 @ T2[:2, :2].T + T2[:2, 2]
    H = T2_inverse @ null_vector(_homography_rows(n1, n2)).reshape(*x1.shape[:-2], 3, 3) @ T1
    return H / np.linalg.norm(H, axis=(-2, -1), keepdims=True)


def homography_dlt(uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """Normalized DLT: x2 ~ H x1 in least squares from N >= 4 correspondences (Hartley normalization)."""
    T2 = hartley_normalization(uv2).T
    return _dlt(uv1, uv2, hartley_normalization(uv1).T, T2, inv(T2))


def transfer_error(H: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> np.ndarray:
    """||pi(H x1) - x2|| in pixels; H may be batched (B, 3, 3) -> (B, N); inf where H x1 is at infinity."""
    # H x1 of every model as one matrix product (rows of all models stacked), as in sampson_residual.
    models = H.shape[:-2]
    mapped = (H[..., :2].reshape(-1, 2) @ uv1.T + H[..., 2].reshape(-1, 1)).reshape(*models, 3, len(uv1))
    w = mapped[..., 2, :]
    finite = np.abs(w) > 1e-12
    safe = np.where(finite, w, 1.0)
    du, dv = mapped[..., 0, :] / safe - uv2[:, 0], mapped[..., 1, :] / safe - uv2[:, 1]
    return np.where(finite, np.sqrt(du * du + dv * dv), np.inf)


def ransac_homography(uv1: np.ndarray, uv2: np.ndarray, threshold_px: float, config: RansacConfig
                      ) -> HomographyResult:
    """H maximizing #{transfer error < threshold_px}: minimal 4-point DLT samples in the RANSAC driver,
    each new best H re-fitted by the DLT on its inliers."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    T1, T2 = (hartley_normalization(uv).T if len(uv) else np.eye(3) for uv in (uv1, uv2))
    T2_inverse = inv(T2)          # once per pair, not once per batch of samples
    result = ransac((uv1, uv2), lambda sample1, sample2: _dlt(sample1, sample2, T1, T2, T2_inverse),
                    MIN_CORRESPONDENCES,
                    transfer_error, threshold_px, config,
                    refit=lambda inliers1, inliers2: homography_dlt(inliers1, inliers2)[None],
                    model_name="homography")
    return HomographyResult(H=result.model, inlier_mask=result.inlier_mask, transfer_px=result.residuals,
                            iterations=result.iterations)


def homography_translation(H: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> float:
    """||t|| / d of H_n = K2^-1 H K1 ~ R + t n^T / d, measured as (s1 - s3) / s2 of H_n's singular values:
    0 for a pure rotation, the baseline over the plane's distance for a plane seen from two centres."""
    singular_values = np.linalg.svd(np.linalg.inv(K2) @ H @ K1, compute_uv=False)
    return float((singular_values[0] - singular_values[2]) / singular_values[1])
