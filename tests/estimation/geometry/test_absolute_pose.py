"""P3P and the P3P LO-RANSAC absolute pose against synthetic ground truth with outliers."""

import warnings

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.absolute_pose import absolute_pose_ransac, epnp, p3p, p3p_batch
from estimation.geometry.alignment import rotation_angle_deg
from estimation.synthetic import make_scene


def correspondences(scene, image):
    in_image = scene.tracks.image_index == image
    return (scene.points[scene.tracks.track_index[in_image]], scene.tracks.uv[in_image],
            scene.inlier_mask[in_image])


def test_one_of_the_p3p_solutions_is_the_true_pose():
    scene = make_scene(num_points=3, seed=1)
    points, uv, _ = correspondences(scene, 2)
    solutions = p3p(scene.K, points, uv)
    assert 1 <= len(solutions) <= 4
    truth = scene.poses[2]
    best = min(solutions, key=lambda pose: rotation_angle_deg(pose.R, truth.R))
    np.testing.assert_allclose(best.R, truth.R, atol=1e-8)
    np.testing.assert_allclose(best.t, truth.t, atol=1e-8)


def random_samples_in_front(num_samples, seed):
    """Samples of three points 2 to 6 units in front of random cameras: (K, points, uv, true [R | t])."""
    rng = np.random.default_rng(seed)
    K = np.array([[300.0, 0, 100], [0, 300, 100], [0, 0, 1]])
    R = Rotation.random(num_samples, random_state=seed).as_matrix()
    t = rng.normal(size=(num_samples, 3))
    in_camera = np.concatenate(
        [rng.uniform(-1, 1, (num_samples, 3, 2)), rng.uniform(2, 6, (num_samples, 3, 1))], axis=2)
    uv = (in_camera[..., :2] / in_camera[..., 2:]) * 300.0 + 100.0
    points = np.einsum("bji,bkj->bki", R, in_camera - t[:, None])             # X = R^T (x_cam - t)
    return K, points, uv, np.concatenate([R, t[:, :, None]], axis=2)


def test_batched_p3p_recovers_every_true_pose_exactly_with_the_points_in_front():
    K, points, uv, truth = random_samples_in_front(500, seed=4)
    solutions = p3p_batch(K, points, uv)
    assert set(solutions.sample_index) == set(range(500))
    closest = np.full(500, np.inf)
    np.minimum.at(closest, solutions.sample_index,
                  np.abs(solutions.poses - truth[solutions.sample_index]).max(axis=(1, 2)))
    assert closest.max() < 1e-8
    R, t = solutions.poses[:, :, :3], solutions.poses[:, :, 3]
    depths = np.einsum("mj,mkj->mk", R[:, 2], points[solutions.sample_index]) + t[:, 2:3]
    assert np.all(depths > 0)


def test_batched_p3p_finds_the_same_poses_as_opencv():
    K, points, uv, _ = random_samples_in_front(300, seed=5)
    solutions = p3p_batch(K, points, uv)
    for sample in range(300):
        _, rvecs, tvecs = cv2.solveP3P(points[sample], np.ascontiguousarray(uv[sample]), K, None,
                                       flags=cv2.SOLVEPNP_P3P)
        ours = solutions.poses[solutions.sample_index == sample]
        assert len(ours) == len(rvecs)
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
            theirs = np.concatenate([cv2.Rodrigues(rvec)[0], tvec.reshape(3, 1)], axis=1)
            assert np.abs(ours - theirs).max(axis=(1, 2)).min() < 1e-6


def test_batched_p3p_gives_no_pose_for_a_sample_repeating_a_point():
    K, points, uv, _ = random_samples_in_front(2, seed=6)
    points[1, 2], uv[1, 2] = points[1, 1], uv[1, 1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solutions = p3p_batch(K, points, uv)
    assert set(solutions.sample_index) == {0}


def test_p3p_takes_exactly_three_correspondences():
    with pytest.raises(DegenerateConfigurationError, match="exactly 3"):
        p3p(np.eye(3), np.zeros((4, 3)), np.zeros((4, 2)))


def test_epnp_is_exact_without_noise():
    scene = make_scene(num_points=20, seed=2)
    points, uv, _ = correspondences(scene, 1)
    pose = epnp(scene.K, points, uv)
    assert rotation_angle_deg(pose.R, scene.poses[1].R) < 1e-6
    np.testing.assert_allclose(pose.t, scene.poses[1].t, atol=1e-6)


def test_lo_ransac_finds_the_pose_and_the_inliers_among_half_outliers():
    scene = make_scene(num_points=400, noise_px=0.5, outlier_fraction=0.5, seed=3)
    points, uv, truly_inlier = correspondences(scene, 3)
    result = absolute_pose_ransac(scene.K, points, uv, RansacConfig())
    truth = scene.poses[3]
    assert rotation_angle_deg(result.pose.R, truth.R) < 0.05
    assert np.linalg.norm(result.pose.center - truth.center) < 0.005 * np.linalg.norm(truth.center)
    assert (result.inlier_mask & ~truly_inlier).sum() <= 1
    assert result.inlier_mask.sum() >= 0.98 * truly_inlier.sum()
    assert result.iterations < RansacConfig().max_iterations      # adaptive stop with P3P's 3-point samples


def test_lo_ransac_needs_six_correspondences_and_a_consensus():
    with pytest.raises(DegenerateConfigurationError, match="6\\+ 2D-3D correspondences"):
        absolute_pose_ransac(np.eye(3), np.zeros((5, 3)), np.zeros((5, 2)), RansacConfig())
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    points = rng.uniform(-1, 1, (30, 3)) + [0, 0, 5]
    with pytest.raises(DegenerateConfigurationError):
        absolute_pose_ransac(K, points, rng.uniform(0, 640, (30, 2)),
                             RansacConfig(pnp_threshold_px=0.01, max_iterations=256))
