"""Linear (DLT) and non-linear triangulation, and triangulation angles, against synthetic ground truth."""

import numpy as np
import pytest

from estimation.geometry.projection import Observations, reprojection_errors, reprojection_residuals
from estimation.geometry.triangulation import (
    _projection_jacobian,
    observations_for_pair,
    ray_pair_angle_deg,
    sum_per_point,
    triangulate_linear,
    triangulate_nonlinear,
    triangulate_ransac,
    triangulation_angle_deg,
    triangulation_angle_reaches,
)
from estimation.synthetic import make_scene
from estimation.types import CameraPose


def all_view_observations(scene) -> Observations:
    t = scene.tracks
    return Observations(
        R=np.stack([scene.poses[m].R for m in t.image_index]),
        t=np.stack([scene.poses[m].t for m in t.image_index]),
        uv=t.uv, point_index=t.track_index, num_points=t.num_tracks,
    )


def test_linear_triangulation_is_exact_without_noise_for_two_views():
    scene = make_scene(num_points=200)
    ids, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    a, b = scene.poses[0], scene.poses[1]
    obs = observations_for_pair(a.R, a.t, b.R, b.t, uv1, uv2)
    result = triangulate_linear(scene.K, obs)
    np.testing.assert_allclose(result.points, scene.points[ids], atol=1e-9)
    assert reprojection_errors(scene.K, obs, result.points).max() < 1e-8


def test_linear_triangulation_uses_every_view_of_a_multi_view_track():
    scene = make_scene(num_cameras=6, num_points=300, visibility=0.5, seed=1)
    result = triangulate_linear(scene.K, all_view_observations(scene))
    np.testing.assert_allclose(result.points, scene.points, atol=1e-9)


def squared_error_per_point(K, obs, points):
    squared = (reprojection_residuals(K, obs, points) ** 2).sum(axis=1)
    return np.bincount(obs.point_index, weights=squared, minlength=obs.num_points)


def test_nonlinear_triangulation_lowers_the_squared_reprojection_error_of_every_point():
    scene = make_scene(num_points=2000, noise_px=2.0, seed=2)
    obs = all_view_observations(scene)
    linear = triangulate_linear(scene.K, obs)
    nonlinear = triangulate_nonlinear(scene.K, obs, linear.points)
    cost_linear = squared_error_per_point(scene.K, obs, linear.points)
    cost_nonlinear = squared_error_per_point(scene.K, obs, nonlinear.points)
    assert np.all(cost_nonlinear <= cost_linear * (1 + 1e-12))
    assert cost_nonlinear.sum() < 0.99 * cost_linear.sum()
    # And the points get closer to the truth on average (the ML estimate under Gaussian pixel noise).
    error_linear = np.linalg.norm(linear.points - scene.points, axis=1).mean()
    error_nonlinear = np.linalg.norm(nonlinear.points - scene.points, axis=1).mean()
    assert error_nonlinear < error_linear


def test_the_projection_jacobian_is_the_derivative_of_the_residuals_with_a_skewed_K():
    scene = make_scene(num_points=50, seed=5)
    obs = all_view_observations(scene)
    K = scene.K + np.array([[0.0, 3.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    step = 1e-6
    numeric = np.stack([(reprojection_residuals(K, obs, scene.points + step * np.eye(3)[k])
                         - reprojection_residuals(K, obs, scene.points - step * np.eye(3)[k])) / (2 * step)
                        for k in range(3)], axis=2)
    np.testing.assert_allclose(_projection_jacobian(K, obs, scene.points), numeric, rtol=1e-5, atol=1e-6)


def test_nonlinear_triangulation_converges_from_a_poor_start():
    scene = make_scene(num_points=500, seed=3)
    obs = all_view_observations(scene)
    start = scene.points + np.random.default_rng(0).normal(0, 0.2, scene.points.shape)
    result = triangulate_nonlinear(scene.K, obs, start)
    np.testing.assert_allclose(result.points, scene.points, atol=1e-7)


def test_noisy_triangulation_error_is_small_relative_to_the_scene():
    scene = make_scene(num_points=500, noise_px=0.5, seed=4)
    obs = all_view_observations(scene)
    result = triangulate_nonlinear(scene.K, obs, triangulate_linear(scene.K, obs).points)
    assert np.median(np.linalg.norm(result.points - scene.points, axis=1)) < 0.001 * scene.scene_size
    assert np.median(reprojection_errors(scene.K, obs, result.points)) == pytest.approx(0.5, rel=0.5)


def test_triangulation_angle_is_the_largest_angle_between_viewing_rays():
    # Cameras at x = -1, 0, +1 on the x axis; the point 1 unit ahead sees them at -45, 0, +45 degrees.
    centers = np.array([[-1.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0], [0.5, 0, 0]])
    point_index = np.array([0, 0, 0, 1, 1])
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1e6]])
    angles = triangulation_angle_deg(centers, point_index, points)
    assert angles[0] == pytest.approx(90.0)
    assert angles[1] == pytest.approx(np.degrees(0.5e-6), rel=1e-3)


def test_the_angle_of_two_rays_per_point_is_triangulation_angle_deg_bitwise():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(500, 3)) * 4.0
    centers = rng.normal(size=(1000, 3))
    centers[7] = points[7]   # a zero ray: NaN in both
    with np.errstate(invalid="ignore"):
        pair = ray_pair_angle_deg(centers, points)
        general = triangulation_angle_deg(centers, np.tile(np.arange(500), 2), points)
    np.testing.assert_array_equal(pair, general)
    assert np.isnan(pair[7]) and np.all(np.isfinite(np.delete(pair, 7)))


def rays_at_angles(angles_deg: np.ndarray, point_index: np.ndarray, num_points: int):
    """Centres on the unit circle around each point at the origin-relative angles, (centres, points)."""
    points = np.arange(num_points)[:, None] * [10.0, 0.0, 0.0]
    angles = np.radians(angles_deg)
    centers = points[point_index] - np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], axis=1)
    return centers, points


def test_the_angle_test_decides_a_middle_reference_ray_by_the_exact_largest_angle():
    # Rays at -1, +1, 0 deg: 1 deg from the middle one, 2 deg apart; 0, 0.5, 1 deg: never 1.5 apart. The
    # answer holds whichever ray is the reference (the two orders give the first point different ones).
    angles = np.array([-1.0, 1.0, 0.0, 0.0, 1.0, 0.5, 0.0, 1.5])
    point_index = np.array([0, 0, 0, 1, 1, 1, 2, 2])
    centers, points = rays_at_angles(angles, point_index, 3)
    for order in (np.arange(8), np.array([1, 2, 0, 5, 4, 3, 7, 6])):
        reaches = triangulation_angle_reaches(centers[order], point_index[order], points, 1.5 - 1e-9)
        np.testing.assert_array_equal(reaches, [True, False, True])


def test_the_angle_test_agrees_with_the_largest_angle_on_random_rays_near_the_limit():
    rng = np.random.default_rng(9)
    point_index = np.sort(rng.integers(0, 400, 2000))
    angles = rng.uniform(-1.2, 1.2, 2000) + rng.normal(0.0, 0.3, 400)[point_index]
    centers, points = rays_at_angles(angles, point_index, 400)
    largest = triangulation_angle_deg(centers, point_index, points)
    assert 50 < (largest >= 1.5).sum() < 350                     # many on either side of the limit
    for min_angle in (0.5, 1.5, 2.0):
        np.testing.assert_array_equal(triangulation_angle_reaches(centers, point_index, points, min_angle),
                                      largest >= min_angle)
    no_rays = triangulation_angle_reaches(centers[:0], point_index[:0], points, 1.5)
    np.testing.assert_array_equal(no_rays, False)


def test_robust_triangulation_rejects_the_outlier_observation_of_each_point_even_in_its_first_pair():
    scene = make_scene(num_points=100, seed=8)
    obs = all_view_observations(scene)
    first_of_point = np.unique(obs.point_index, return_index=True)[1]
    corrupted = np.zeros(len(obs.uv), bool)
    corrupted[first_of_point] = True
    obs = obs._replace(uv=obs.uv + 30.0 * corrupted[:, None])
    result = triangulate_ransac(scene.K, obs, max_error_px=2.0, min_angle_deg=1.0, hypotheses_per_point=8)
    assert result.valid.all()
    np.testing.assert_array_equal(result.inlier_mask, ~corrupted)
    np.testing.assert_allclose(result.points, scene.points, atol=1e-7)


def test_robust_triangulation_of_two_observations_is_their_two_view_point():
    scene = make_scene(num_points=50, seed=9)
    ids, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    a, b = scene.poses[0], scene.poses[1]
    result = triangulate_ransac(scene.K, observations_for_pair(a.R, a.t, b.R, b.t, uv1, uv2),
                                max_error_px=2.0, min_angle_deg=1.0, hypotheses_per_point=8)
    assert result.valid.all() and result.inlier_mask.all()
    np.testing.assert_allclose(result.points, scene.points[ids], atol=1e-7)


def test_sum_per_point_adds_each_observations_block_to_its_point_and_zero_to_unobserved_ones():
    values = np.arange(24.0).reshape(4, 2, 3)
    sums = sum_per_point(values, np.array([2, 0, 2, 0]), num_points=4)
    np.testing.assert_array_equal(sums[0], values[1] + values[3])
    np.testing.assert_array_equal(sums[2], values[0] + values[2])
    np.testing.assert_array_equal(sums[[1, 3]], np.zeros((2, 2, 3)))


def test_observations_for_pair_lists_both_cameras_per_point():
    pose = CameraPose(R=np.eye(3), t=np.array([1.0, 0, 0]))
    obs = observations_for_pair(np.eye(3), np.zeros(3), pose.R, pose.t, np.zeros((3, 2)), np.ones((3, 2)))
    assert obs.num_points == 3
    np.testing.assert_array_equal(obs.point_index, [0, 1, 2, 0, 1, 2])
    np.testing.assert_array_equal(obs.t[3:], np.tile([1.0, 0, 0], (3, 1)))
