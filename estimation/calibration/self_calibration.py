"""A focal length from the verified pairs' fundamental matrices alone (self-calibration), to start from.

Under the true intrinsics K, E = K^T F K of every pair is an essential matrix: two equal singular values
and a zero one (Mendonca and Cipolla). With the principal point at the image centre and one focal length
f shared by every photo, the inlier-weighted mean of (s_1 - s_2) / (s_1 + s_2) over the pairs is a cost
of f alone, minimised on a log-spaced grid around the prior. The bundle adjustment refines f anyway;
what this saves is its crawl from a prior 20-40 % off along the two- and three-view focal length/depth
valley (fountain-P11's first two BAs took 115 iterations from the 1.2 max(w, h) prior). The estimate is
refused (None) when the cost has no clear minimum inside the search range: when every optical axis
passes through one point (an object ring, a turntable) F says nothing about f, and the cost falls
towards the range's edge.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

GRID_STEP = 0.01
"""Relative step of the focal length grid (a starting point: 1 % is well within what the BA moves)."""
BRACKET = 1.25
"""A minimum counts when the cost at f / BRACKET and f * BRACKET both exceed it by the contrast asked."""
MAX_PAIRS = 200
"""The pairs with most inliers that vote (the cost of a large set's thousands of pairs, for nothing)."""


class FocalFromPairs(NamedTuple):
    """The focal length that makes the pairs' E most nearly essential, or None, and why."""

    focal_px: float | None       # None: no clear minimum (keep the prior)
    grid_minimum_px: float       # where the cost is lowest on the grid (even when refused)
    contrast: float              # min(cost(f / BRACKET), cost(f * BRACKET)) / cost(f) at that minimum
    pairs: int
    reason: str                  # why it was refused ("" when accepted)


def essential_defect(F: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(s_1 - s_2) / (s_1 + s_2) of each E = K^T F K: 0 for an essential matrix. F (N, 3, 3) pixel
    fundamental matrices, K (M, 3, 3) candidate intrinsics; returns (M, N)."""
    E = np.einsum("mji,njk,mkl->mnil", K, F, K)
    singular = np.linalg.svd(E, compute_uv=False)
    return (singular[..., 0] - singular[..., 1]) / np.maximum(singular[..., 0] + singular[..., 1], 1e-300)


def focal_from_fundamentals(F: np.ndarray, weights: np.ndarray, principal_point: tuple[float, float],
                            prior_px: float, search_factor: float, min_contrast: float) -> FocalFromPairs:
    """f = argmin_f sum_k w_k defect_k(f) / sum_k w_k over f in [prior / search_factor, prior *
    search_factor] (`essential_defect` under K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]), accepted when it
    lies at least BRACKET inside the range and the cost BRACKET away on both sides is min_contrast times
    its value or more. F (N, 3, 3) pixel fundamental matrices of the pairs, weights (N,) their inliers."""
    F, weights = np.asarray(F, float).reshape(-1, 3, 3), np.asarray(weights, float).reshape(-1)
    strongest = np.argsort(-weights, kind="stable")[:MAX_PAIRS]
    F, weights = F[strongest], weights[strongest]
    if len(F) == 0:
        return FocalFromPairs(None, float("nan"), float("nan"), 0, "no verified pair with F")
    steps = int(np.ceil(np.log(search_factor) / np.log1p(GRID_STEP)))
    focals = prior_px * (1.0 + GRID_STEP) ** np.arange(-steps, steps + 1)
    K = np.zeros((len(focals), 3, 3))
    K[:, 0, 0] = K[:, 1, 1] = focals
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = principal_point[0], principal_point[1], 1.0
    cost = essential_defect(F, K) @ weights / weights.sum()
    best = int(np.argmin(cost))
    focal = float(focals[best])
    sides = np.interp(np.log([focal / BRACKET, focal * BRACKET]), np.log(focals), cost)
    contrast = float(sides.min() / max(cost[best], 1e-300))
    if not focals[0] * BRACKET <= focal <= focals[-1] / BRACKET:
        reason = (f"the pairs' cost falls towards the edge of the search range ({focal:.1f} px): F does not "
                  "determine the focal length (optical axes through one point?)")
    elif contrast < min_contrast:
        reason = f"the pairs' cost has no clear minimum (contrast {contrast:.2f}, need {min_contrast:g})"
    else:
        reason = ""
    return FocalFromPairs(None if reason else focal, focal, contrast, len(F), reason)
