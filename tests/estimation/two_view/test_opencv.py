"""F, E and H by OpenCV's RANSAC with the project's LO and residuals, against synthetic ground truth."""

import numpy as np
import pytest

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.alignment import relative_pose, rotation_angle_deg
from estimation.synthetic import make_scene
from estimation.two_view.essential import choose_relative_pose, fundamental_from_essential, polish_essential
from estimation.two_view.fundamental import sampson_distance
from estimation.two_view.homography import transfer_error
from estimation.two_view.opencv import opencv_essential, opencv_fundamental, opencv_homography

H_TRUE = np.array([[0.9, -0.1, 30.0], [0.12, 1.05, -12.0], [1e-4, -2e-4, 1.0]])


def noisy_pair(i, j, seed=1):
    scene = make_scene(num_points=500, noise_px=0.5, outlier_fraction=0.3, seed=seed)
    track_ids, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
    truly_inlier = scene.inlier_mask.reshape(-1, 5)[track_ids][:, [i, j]].all(axis=1)
    return scene, uv1, uv2, truly_inlier


def assert_separates(mask, truly_inlier):
    assert (mask & truly_inlier).sum() / mask.sum() > 0.97
    assert (mask & truly_inlier).sum() / truly_inlier.sum() > 0.9


def test_fundamental_inliers_are_the_true_correspondences_by_the_projects_sampson_distance():
    _, uv1, uv2, truly_inlier = noisy_pair(0, 1)
    result = opencv_fundamental(uv1, uv2, 1.5, RansacConfig())
    assert_separates(result.inlier_mask, truly_inlier)
    np.testing.assert_allclose(result.sampson_px, sampson_distance(result.F, uv1, uv2))
    np.testing.assert_array_equal(result.inlier_mask, result.sampson_px < 1.5)
    assert np.linalg.matrix_rank(result.F, tol=1e-9) == 2 and np.isclose(np.linalg.norm(result.F), 1.0)


@pytest.mark.parametrize("pair", [(0, 1), (0, 4), (2, 3)])
def test_essential_under_noise_and_30_percent_outliers_polished_gives_the_pose_within_0_2_degrees(pair):
    i, j = pair
    scene, uv1, uv2, truly_inlier = noisy_pair(i, j)
    result = opencv_essential(uv1, uv2, scene.K, scene.K, 1.5, RansacConfig())
    assert_separates(result.inlier_mask, truly_inlier)
    F = fundamental_from_essential(result.E, scene.K, scene.K)
    np.testing.assert_allclose(result.sampson_px, sampson_distance(F, uv1, uv2))
    polished = polish_essential(result, uv1, uv2, scene.K, scene.K, 1.5)      # as the initial pair does
    assert polished.inlier_mask.sum() >= result.inlier_mask.sum()
    inliers = polished.inlier_mask
    chosen = choose_relative_pose(polished.E, scene.K, uv1[inliers], uv2[inliers])
    assert rotation_angle_deg(chosen.pose.R, relative_pose(scene.poses[i], scene.poses[j]).R) < 0.2


def test_homography_keeps_the_correspondences_it_maps_within_the_threshold():
    rng = np.random.default_rng(0)
    uv1 = rng.uniform([0, 0], [640, 480], (300, 2))
    mapped = np.c_[uv1, np.ones(300)] @ H_TRUE.T
    exact = mapped[:, :2] / mapped[:, 2:]
    uv2 = exact + rng.normal(0, 0.5, (300, 2))
    outlier = rng.random(300) < 0.3
    uv2[outlier] += rng.uniform(20, 200, (outlier.sum(), 2)) * rng.choice([-1, 1], (outlier.sum(), 2))
    result = opencv_homography(uv1, uv2, 3.0, RansacConfig())
    np.testing.assert_array_equal(result.inlier_mask, ~outlier)
    assert np.median(transfer_error(result.H, uv1[~outlier], exact[~outlier])) < 0.2


@pytest.mark.parametrize("estimate, minimum", [
    (lambda uv: opencv_fundamental(uv, uv, 1.0, RansacConfig()), 8),
    (lambda uv: opencv_essential(uv, uv, np.eye(3), np.eye(3), 1.0, RansacConfig()), 5),
    (lambda uv: opencv_homography(uv, uv, 1.0, RansacConfig()), 4),
])
def test_too_few_correspondences_are_degenerate(estimate, minimum):
    with pytest.raises(DegenerateConfigurationError, match=f"needs at least {minimum}"):
        estimate(np.zeros((minimum - 1, 2)))
