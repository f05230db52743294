"""Geometric verification of an image pair: E (5-point, or from the 8-point F), F and H in RANSAC, and the
pair's two-view geometry type as COLMAP labels it, so that planar and pure-rotation pairs do not start a
model.

The decision (COLMAP's EstimateCalibratedTwoViewGeometry): fewer than min_inliers F inliers is
degenerate; E is trusted when K is known and E explains almost all of F's inliers (min_e_f_inlier_ratio),
F otherwise. When H explains most of those inliers (max_h_inlier_ratio) the pair is planar or a pure
rotation; with K, the two are told apart by H's normalized singular values (baseline over plane distance
below max_rotation_translation: panoramic).

It is made in two steps: `verify_epipolar` (F, E: the inliers, and whether the pair is degenerate,
calibrated or uncalibrated), then `classify_planarity` (H: whether it is planar or panoramic instead). The
second never changes the inliers, so the front end may leave it for later (`features.planarity`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum
from functools import partial

import numpy as np

from estimation.config import RansacConfig, TwoViewConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.ransac import required_iterations
from estimation.two_view.essential import (
    FIVE_POINT_SAMPLE,
    fundamental_from_essential,
    polish_essential,
    project_to_essential,
    ransac_essential,
)
from estimation.two_view.fundamental import ransac_fundamental, sampson_distance
from estimation.two_view.homography import MIN_CORRESPONDENCES as H_SAMPLE
from estimation.two_view.homography import homography_translation, ransac_homography
from estimation.two_view.opencv import opencv_essential, opencv_fundamental, opencv_homography


class TwoViewGeometryType(StrEnum):
    """COLMAP's two-view geometry configurations."""

    CALIBRATED = "calibrated"                    # E with general motion and 3D structure
    UNCALIBRATED = "uncalibrated"                # F with general motion and 3D structure
    PLANAR = "planar"                            # H of a scene plane seen from two centres
    PANORAMIC = "panoramic"                      # H of a pure rotation (no baseline)
    PLANAR_OR_PANORAMIC = "planar_or_panoramic"  # H without K: the two cannot be told apart
    DEGENERATE = "degenerate"                    # too few inliers for any model


INITIALIZABLE = (TwoViewGeometryType.CALIBRATED, TwoViewGeometryType.UNCALIBRATED)


@dataclass(frozen=True)
class TwoViewGeometry:
    """The verified geometry of one pair; `inlier_mask` is the inliers of the model the type rests on
    (E when calibrated or planar/panoramic with K, F when uncalibrated, H when only H fits)."""

    type: TwoViewGeometryType
    inlier_mask: np.ndarray          # (N,) bool
    F: np.ndarray | None             # pixel coordinates: x2^T F x1 = 0
    E: np.ndarray | None             # normalized coordinates (K known)
    H: np.ndarray | None             # pixel coordinates: x2 ~ H x1
    num_inliers_f: int
    num_inliers_e: int
    num_inliers_h: int
    planarity_tested: bool = True    # False: H not estimated yet (`classify_planarity` may change the type)

    @property
    def num_inliers(self) -> int:
        return int(self.inlier_mask.sum())

    @property
    def h_e_inlier_ratio(self) -> float:
        """H inliers over E inliers (over F inliers without K): near 1 for planar or rotating pairs."""
        reference = self.num_inliers_e if self.E is not None else self.num_inliers_f
        return self.num_inliers_h / reference if reference else 0.0

    @property
    def can_initialize(self) -> bool:
        """General motion with 3D structure: a pair a model may start from."""
        return self.type in INITIALIZABLE


def _robust(estimate, *args):
    """The estimator's result, or None when RANSAC finds no model."""
    try:
        return estimate(*args)
    except DegenerateConfigurationError:
        return None


def _search(ransac: RansacConfig, share: float, sample_size: int) -> RansacConfig:
    """The RANSAC settings that find, with the configured confidence, a model explaining `share` of the
    matches: a model needs that many inliers to change the decision, so no more samples."""
    needed = required_iterations(min(share, 1.0), sample_size, ransac.confidence, ransac.max_iterations)
    return ransac.model_copy(update={"max_iterations": needed})


def verify_epipolar(uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray | None, K2: np.ndarray | None,
                    config: TwoViewConfig, ransac: RansacConfig, refine_essential: bool = True
                    ) -> TwoViewGeometry:
    """F (8-point) and E (5-point, or E = K^T F K under relative_pose "eight-point"; only with K) in RANSAC
    at max_error_px: the pair's inliers and its type as far as they decide it (degenerate, calibrated or
    uncalibrated); the planarity test (H) is left to `classify_planarity` (`planarity_tested` False).

    `config.estimator` says whose RANSAC (the project's or OpenCV's); `refine_essential`: polish the
    5-point E non-linearly on its inliers (`polish_essential`); needed where E's pose is used (the initial
    pair), not where only the type and the inliers are (matching)."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    threshold = config.max_error_px
    ransac = ransac.model_copy(update={"threshold_px": threshold})
    calibrated = K1 is not None and K2 is not None
    none = np.zeros(len(uv1), bool)

    opencv = config.estimator == "opencv"
    fundamental = (_robust(opencv_fundamental, uv1, uv2, threshold, ransac) if opencv
                   else _robust(ransac_fundamental, uv1, uv2, ransac))
    if fundamental is None or fundamental.inlier_mask.sum() < config.min_inliers:
        # Every pair that E or H explains satisfies an F too: too few F inliers leave too few for them.
        return TwoViewGeometry(type=TwoViewGeometryType.DEGENERATE, inlier_mask=none,
                               F=fundamental.F if fundamental else None, E=None, H=None,
                               num_inliers_f=int(fundamental.inlier_mask.sum()) if fundamental else 0,
                               num_inliers_e=0, num_inliers_h=0)
    F, f_mask = fundamental.F, fundamental.inlier_mask
    num_f = int(f_mask.sum())

    E, e_mask = None, none
    if calibrated and config.relative_pose == "five-point":
        search = _search(ransac, config.min_e_f_inlier_ratio * num_f / len(uv1), FIVE_POINT_SAMPLE)
        estimator = opencv_essential if opencv else partial(ransac_essential, refine=False)
        essential = _robust(estimator, uv1, uv2, K1, K2, threshold, search)
        if essential is not None and refine_essential:
            essential = polish_essential(essential, uv1, uv2, K1, K2, threshold)
        if essential is not None:
            E, e_mask = essential.E, essential.inlier_mask
    elif calibrated:
        E = project_to_essential(K2.T @ F @ K1)        # the seed's E = K^T F K
        e_mask = sampson_distance(fundamental_from_essential(E, K1, K2), uv1, uv2) < threshold
    num_e = int(e_mask.sum())
    use_e = E is not None and num_e >= config.min_inliers and num_e >= config.min_e_f_inlier_ratio * num_f
    return TwoViewGeometry(
        type=TwoViewGeometryType.CALIBRATED if use_e else TwoViewGeometryType.UNCALIBRATED,
        inlier_mask=e_mask if use_e else f_mask, F=F, E=E, H=None, num_inliers_f=num_f, num_inliers_e=num_e,
        num_inliers_h=0, planarity_tested=False)


def classify_planarity(geometry: TwoViewGeometry, uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray | None,
                       K2: np.ndarray | None, config: TwoViewConfig, ransac: RansacConfig) -> TwoViewGeometry:
    """H (4-point) in RANSAC at max_error_px on the pair of `verify_epipolar`: planar or panoramic
    (planar_or_panoramic without E) when it explains over max_h_inlier_ratio of the inliers the type rests
    on. The inliers stay the same: only the type can change, so the tracks never depend on this test."""
    if geometry.planarity_tested:
        return geometry
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    threshold = config.max_error_px      # the H estimators take it as is (not from `ransac`)
    use_e = geometry.type == TwoViewGeometryType.CALIBRATED
    num_reference = geometry.num_inliers_e if use_e else geometry.num_inliers_f
    estimator = opencv_homography if config.estimator == "opencv" else ransac_homography
    homography = _robust(estimator, uv1, uv2, threshold,
                         _search(ransac, config.max_h_inlier_ratio * num_reference / len(uv1), H_SAMPLE))
    H = homography.H if homography is not None else None
    num_h = int(homography.inlier_mask.sum()) if homography is not None else 0
    type_ = geometry.type
    if num_h > config.max_h_inlier_ratio * num_reference:
        if not use_e:
            type_ = TwoViewGeometryType.PLANAR_OR_PANORAMIC
        elif homography_translation(H, K1, K2) < config.max_rotation_translation:
            type_ = TwoViewGeometryType.PANORAMIC
        else:
            type_ = TwoViewGeometryType.PLANAR
    return replace(geometry, type=type_, H=H, num_inliers_h=num_h, planarity_tested=True)


def estimate_two_view_geometry(uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray | None, K2: np.ndarray | None,
                               config: TwoViewConfig, ransac: RansacConfig, refine_essential: bool = True
                               ) -> TwoViewGeometry:
    """F, E and H in RANSAC and the pair's type from their inlier counts: `verify_epipolar`, then
    `classify_planarity`."""
    geometry = verify_epipolar(uv1, uv2, K1, K2, config, ransac, refine_essential)
    return classify_planarity(geometry, uv1, uv2, K1, K2, config, ransac)
