"""F, E and H in OpenCV's compiled RANSAC (cv2.findFundamentalMat / findEssentialMat / findHomography):
the same minimal solvers as the project's own (7/8-point F, Nister's 5-point E, 4-point H), without
Python's per-hypothesis overhead, for verifying many pairs.

cv2's plain RANSAC has no local optimization: its model is then re-fitted on its inliers by the
project's non-minimal solvers (8-point F, 8-point E projected to an essential matrix, DLT H) as the
project's LO-RANSAC does (`ransac.locally_optimized`), with the inliers scored by the project's residuals
(Sampson distance in pixels for F and E, transfer error for H) at the same threshold, so both estimators
label pairs by the same measure. cv2 does not report how many samples it drew: `iterations` holds the
cap it was given.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.ransac import locally_optimized
from estimation.two_view.essential import (
    FIVE_POINT_SAMPLE,
    EssentialResult,
    fundamental_from_essential,
    project_to_essential,
    to_normalized,
)
from estimation.two_view.fundamental import MIN_CORRESPONDENCES as F_SAMPLE
from estimation.two_view.fundamental import FundamentalResult, eight_point, sampson_distance
from estimation.two_view.homography import MIN_CORRESPONDENCES as H_SAMPLE
from estimation.two_view.homography import HomographyResult, homography_dlt, transfer_error


def _require(num: int, sample_size: int, model_name: str) -> None:
    if num < sample_size:
        raise DegenerateConfigurationError(
            f"a {model_name} needs at least {sample_size} correspondences, got {num}"
        )


def opencv_fundamental(uv1: np.ndarray, uv2: np.ndarray, threshold_px: float, config: RansacConfig
                       ) -> FundamentalResult:
    """F maximizing #{Sampson distance < threshold_px}: cv2's FM_RANSAC, then LO by the 8-point."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    _require(len(uv1), F_SAMPLE, "fundamental matrix")
    F, _ = cv2.findFundamentalMat(uv1, uv2, cv2.FM_RANSAC, threshold_px, config.confidence,
                                  config.max_iterations)
    F, distance = _locally_optimized_3x3(F, "fundamental matrix", uv1, uv2, sampson_distance, eight_point,
                                         threshold_px, config)
    return FundamentalResult(F=F, inlier_mask=distance < threshold_px, sampson_px=distance,
                             iterations=config.max_iterations)


def opencv_essential(uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold_px: float,
                     config: RansacConfig) -> EssentialResult:
    """E maximizing #{Sampson distance of F = K2^-T E K1^-1 < threshold_px}: cv2's 5-point RANSAC on the
    normalized points (threshold divided by the mean focal length); of its roots, the one with most
    inliers by the pixel Sampson distance, then LO by the 8-point on normalized inliers."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    _require(len(uv1), FIVE_POINT_SAMPLE, "essential matrix")
    focal = np.mean([K1[0, 0], K1[1, 1], K2[0, 0], K2[1, 1]])
    E, _ = cv2.findEssentialMat(to_normalized(K1, uv1), to_normalized(K2, uv2), np.eye(3), cv2.RANSAC,
                                config.confidence, threshold_px / focal, config.max_iterations)
    if E is None or E.shape[0] < 3:
        raise DegenerateConfigurationError(f"OpenCV's RANSAC found no essential matrix among {len(uv1)} "
                                           "correspondences")

    def residuals(E: np.ndarray, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
        return sampson_distance(fundamental_from_essential(E, K1, K2), points1, points2)

    def refit(inliers1: np.ndarray, inliers2: np.ndarray) -> np.ndarray:
        E = eight_point(to_normalized(K1, inliers1), to_normalized(K2, inliers2))
        return project_to_essential(E)[None]

    candidates = E.reshape(-1, 3, 3)        # a degenerate sample may leave several roots
    scored = residuals(candidates, uv1, uv2)
    best = int(np.argmax((scored < threshold_px).sum(axis=1)))
    E, _, _ = locally_optimized(candidates[best] / np.linalg.norm(candidates[best]), scored[best], (uv1, uv2),
                                residuals, threshold_px, refit, config.local_refits)
    distance = residuals(E[None], uv1, uv2)[0]
    return EssentialResult(E=E, inlier_mask=distance < threshold_px, sampson_px=distance,
                           iterations=config.max_iterations)


def opencv_homography(uv1: np.ndarray, uv2: np.ndarray, threshold_px: float, config: RansacConfig
                      ) -> HomographyResult:
    """H maximizing #{||pi(H x1) - x2|| < threshold_px}: cv2's 4-point RANSAC, then LO by the DLT."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    _require(len(uv1), H_SAMPLE, "homography")
    H, _ = cv2.findHomography(uv1, uv2, cv2.RANSAC, threshold_px, maxIters=config.max_iterations,
                              confidence=config.confidence)
    H, error = _locally_optimized_3x3(H, "homography", uv1, uv2, transfer_error, homography_dlt, threshold_px,
                                      config)
    return HomographyResult(H=H, inlier_mask=error < threshold_px, transfer_px=error,
                            iterations=config.max_iterations)


def _locally_optimized_3x3(model: np.ndarray | None, name: str, uv1: np.ndarray, uv2: np.ndarray,
                           residuals: Callable, solver: Callable, threshold_px: float, config: RansacConfig
                           ) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's 3x3 model after LO by `solver` on its inliers, and its residuals in pixels."""
    if model is None or model.shape != (3, 3):
        raise DegenerateConfigurationError(f"OpenCV's RANSAC found no {name} among {len(uv1)} "
                                           "correspondences")
    model, _, _ = locally_optimized(model / np.linalg.norm(model), residuals(model, uv1, uv2),
                                    (uv1, uv2), residuals, threshold_px,
                                    lambda inliers1, inliers2: solver(inliers1, inliers2)[None],
                                    config.local_refits)
    return model, residuals(model, uv1, uv2)
