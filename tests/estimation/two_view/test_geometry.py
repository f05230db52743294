"""Two-view geometry types: general scenes are calibrated, a plane is planar, a pure rotation panoramic."""

import numpy as np
import pytest

from estimation.config import RansacConfig, TwoViewConfig
from estimation.geometry.alignment import relative_pose, rotation_angle_deg
from estimation.synthetic import make_scene, project, rotation_about_axis
from estimation.two_view.essential import choose_relative_pose
from estimation.two_view.geometry import (
    TwoViewGeometryType,
    classify_planarity,
    estimate_two_view_geometry,
    verify_epipolar,
)
from estimation.types import CameraPose

K = np.array([[600.0, 0.0, 400.0], [0.0, 600.0, 300.0], [0.0, 0.0, 1.0]])
ESTIMATORS = pytest.mark.parametrize("estimator", ["numpy", "opencv"])   # whose RANSAC: same verdicts


def with_noise_and_outliers(uv1, uv2, seed, noise_px=0.5, outlier_fraction=0.3):
    rng = np.random.default_rng(seed)
    uv1 = uv1 + rng.normal(0, noise_px, uv1.shape)
    uv2 = uv2 + rng.normal(0, noise_px, uv2.shape)
    outliers = rng.random(len(uv1)) < outlier_fraction
    uv2[outliers] = rng.uniform([0, 0], [800, 600], (outliers.sum(), 2))
    return uv1, uv2, ~outliers


def two_views(points, second: CameraPose, seed):
    first = CameraPose(R=np.eye(3), t=np.zeros(3))
    return with_noise_and_outliers(project(K, first, points), project(K, second, points), seed)


def visible_points(rng, num, depth=(4.0, 8.0)):
    z = rng.uniform(*depth, num)
    return np.stack([rng.uniform(-0.5, 0.5, num) * z, rng.uniform(-0.4, 0.4, num) * z, z], axis=1)


@ESTIMATORS
@pytest.mark.parametrize("relative_pose_method", ["five-point", "eight-point"])
def test_a_general_scene_is_calibrated_and_its_pose_is_within_0_2_degrees(relative_pose_method, estimator):
    scene = make_scene(num_points=400, seed=6)
    config = TwoViewConfig(relative_pose=relative_pose_method, max_error_px=2.0, estimator=estimator)
    for i, j in [(0, 1), (1, 3)]:
        _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        uv1, uv2, inlier = with_noise_and_outliers(uv1, uv2, seed=i + j)
        geometry = estimate_two_view_geometry(uv1, uv2, scene.K, scene.K, config, RansacConfig())
        assert geometry.type == TwoViewGeometryType.CALIBRATED and geometry.can_initialize
        assert (geometry.inlier_mask & ~inlier).sum() <= 0.02 * geometry.num_inliers
        assert geometry.num_inliers >= 0.95 * inlier.sum()
        assert geometry.h_e_inlier_ratio < 0.8
        inliers = geometry.inlier_mask
        chosen = choose_relative_pose(geometry.E, scene.K, uv1[inliers], uv2[inliers])
        assert rotation_angle_deg(chosen.pose.R, relative_pose(scene.poses[i], scene.poses[j]).R) < 0.2


@ESTIMATORS
def test_a_plane_seen_from_two_centres_is_planar(estimator):
    rng = np.random.default_rng(1)
    points = visible_points(rng, 300)
    points[:, 2] = 6.0 + 0.3 * points[:, 0]                 # a tilted wall
    second = CameraPose.from_center(rotation_about_axis([0, 1, 0], np.deg2rad(-8)), np.array([1.0, 0, 0]))
    uv1, uv2, _ = two_views(points, second, seed=1)
    geometry = estimate_two_view_geometry(uv1, uv2, K, K, TwoViewConfig(estimator=estimator), RansacConfig())
    assert geometry.type == TwoViewGeometryType.PLANAR and not geometry.can_initialize
    assert geometry.h_e_inlier_ratio > 0.8


@ESTIMATORS
def test_a_pure_rotation_is_panoramic(estimator):
    rng = np.random.default_rng(2)
    points = visible_points(rng, 300)
    second = CameraPose(R=rotation_about_axis([0.2, 1.0, 0.1], np.deg2rad(10)), t=np.zeros(3))
    uv1, uv2, _ = two_views(points, second, seed=2)
    geometry = estimate_two_view_geometry(uv1, uv2, K, K, TwoViewConfig(estimator=estimator), RansacConfig())
    assert geometry.type == TwoViewGeometryType.PANORAMIC and not geometry.can_initialize


@ESTIMATORS
def test_without_k_the_types_are_uncalibrated_or_planar_or_panoramic(estimator):
    rng = np.random.default_rng(3)
    general = visible_points(rng, 300)
    second = CameraPose.from_center(rotation_about_axis([0, 1, 0], np.deg2rad(-8)), np.array([1.0, 0, 0]))
    config = TwoViewConfig(estimator=estimator)
    geometry = estimate_two_view_geometry(*two_views(general, second, 3)[:2], None, None, config,
                                          RansacConfig())
    assert geometry.type == TwoViewGeometryType.UNCALIBRATED and geometry.E is None
    rotation = CameraPose(R=second.R, t=np.zeros(3))
    geometry = estimate_two_view_geometry(*two_views(general, rotation, 3)[:2], None, None, config,
                                          RansacConfig())
    assert geometry.type == TwoViewGeometryType.PLANAR_OR_PANORAMIC


@ESTIMATORS
def test_random_correspondences_are_degenerate(estimator):
    rng = np.random.default_rng(4)
    uv1, uv2 = rng.uniform(0, 800, (40, 2)), rng.uniform(0, 800, (40, 2))
    config = TwoViewConfig(max_error_px=1.0, estimator=estimator)
    geometry = estimate_two_view_geometry(uv1, uv2, K, K, config, RansacConfig())
    assert geometry.type == TwoViewGeometryType.DEGENERATE and geometry.num_inliers == 0


def test_the_planarity_test_alone_relabels_a_plane_and_keeps_its_inliers():
    rng = np.random.default_rng(1)
    points = visible_points(rng, 300)
    points[:, 2] = 6.0 + 0.3 * points[:, 0]                 # the tilted wall above
    second = CameraPose.from_center(rotation_about_axis([0, 1, 0], np.deg2rad(-8)), np.array([1.0, 0, 0]))
    uv1, uv2, _ = two_views(points, second, seed=1)
    config, ransac = TwoViewConfig(), RansacConfig()
    epipolar = verify_epipolar(uv1, uv2, K, K, config, ransac)
    assert epipolar.type == TwoViewGeometryType.CALIBRATED and not epipolar.planarity_tested
    assert epipolar.H is None
    classified = classify_planarity(epipolar, uv1, uv2, K, K, config, ransac)
    assert classified.type == TwoViewGeometryType.PLANAR and classified.planarity_tested
    np.testing.assert_array_equal(classified.inlier_mask, epipolar.inlier_mask)
    whole = estimate_two_view_geometry(uv1, uv2, K, K, config, ransac)
    assert whole.type == classified.type and whole.num_inliers_h == classified.num_inliers_h
    np.testing.assert_array_equal(whole.H, classified.H)


def test_a_degenerate_pair_needs_no_planarity_test():
    rng = np.random.default_rng(4)
    uv1, uv2 = rng.uniform(0, 800, (40, 2)), rng.uniform(0, 800, (40, 2))
    geometry = verify_epipolar(uv1, uv2, K, K, TwoViewConfig(max_error_px=1.0), RansacConfig())
    assert geometry.type == TwoViewGeometryType.DEGENERATE and geometry.planarity_tested
