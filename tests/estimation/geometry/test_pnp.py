"""Linear PnP (DLT), PnP RANSAC and non-linear PnP, against synthetic ground truth."""

import numpy as np
import pytest

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.alignment import rotation_angle_deg
from estimation.geometry.pnp import (
    consensus_from_turned_starts,
    pnp_linear,
    pnp_nonlinear,
    pnp_ransac,
    refine_pose,
    reprojection_errors_per_hypothesis,
)
from estimation.geometry.projection import Observations, reprojection_errors
from estimation.synthetic import make_scene, rotation_about_axis
from estimation.types import CameraPose


def correspondences(scene, image):
    in_image = scene.tracks.image_index == image
    return (scene.points[scene.tracks.track_index[in_image]], scene.tracks.uv[in_image],
            scene.inlier_mask[in_image])


def test_linear_pnp_is_exact_from_six_noise_free_correspondences():
    scene = make_scene(num_points=6, seed=1)
    points, uv, _ = correspondences(scene, 2)
    pose = pnp_linear(scene.K, points, uv)
    np.testing.assert_allclose(pose.R, scene.poses[2].R, atol=1e-9)
    np.testing.assert_allclose(pose.t, scene.poses[2].t, atol=1e-9)


def test_linear_pnp_returns_a_proper_rotation_under_noise():
    scene = make_scene(num_points=50, noise_px=3.0, seed=2)
    pose = pnp_linear(scene.K, *correspondences(scene, 1)[:2])
    np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(pose.R) == pytest.approx(1.0)
    assert rotation_angle_deg(pose.R, scene.poses[1].R) < 2.0


def test_fewer_than_six_correspondences_are_degenerate():
    points, uv = np.zeros((5, 3)), np.zeros((5, 2))
    for solve in (lambda: pnp_linear(np.eye(3), points, uv), lambda: pnp_ransac(np.eye(3), points, uv,
                                                                                     RansacConfig())):
        with pytest.raises(DegenerateConfigurationError, match="at least 6"):
            solve()


def test_ransac_pnp_under_noise_and_30_percent_outliers():
    scene = make_scene(num_points=400, noise_px=0.5, outlier_fraction=0.3, seed=3)
    for image in range(5):
        points, uv, truly_inlier = correspondences(scene, image)
        result = pnp_ransac(scene.K, points, uv, RansacConfig())
        assert (result.inlier_mask & ~truly_inlier).sum() <= 2        # random pixels rarely land within 4 px
        assert (result.inlier_mask & truly_inlier).sum() >= 0.98 * truly_inlier.sum()
        truth = scene.poses[image]
        assert rotation_angle_deg(result.pose.R, truth.R) < 0.5
        assert np.linalg.norm(result.pose.center - truth.center) < 0.01 * scene.scene_size


def test_nonlinear_pnp_reaches_the_noise_floor_and_beats_the_linear_pose():
    scene = make_scene(num_points=400, noise_px=0.5, outlier_fraction=0.3, seed=4)
    points, uv, truly_inlier = correspondences(scene, 3)
    ransac = pnp_ransac(scene.K, points, uv, RansacConfig())
    inliers = ransac.inlier_mask
    refined = pnp_nonlinear(scene.K, points[inliers], uv[inliers], ransac.pose)
    truth = scene.poses[3]
    assert refined.final_rms_px < refined.initial_rms_px
    assert refined.final_rms_px == pytest.approx(0.5 * np.sqrt(2), rel=0.15)   # 2D noise of 0.5 px per axis
    assert rotation_angle_deg(refined.pose.R, truth.R) < 0.05
    assert np.linalg.norm(refined.pose.center - truth.center) < 0.001 * scene.scene_size


def test_nonlinear_pnp_recovers_a_perturbed_pose_exactly_without_noise():
    scene = make_scene(num_points=100, seed=5)
    points, uv, _ = correspondences(scene, 0)
    truth = scene.poses[0]
    start = CameraPose(R=rotation_about_axis(np.array([1.0, 1.0, 0.0]), 0.05) @ truth.R, t=truth.t + 0.1)
    refined = pnp_nonlinear(scene.K, points, uv, start)
    assert rotation_angle_deg(refined.pose.R, truth.R) < 1e-6
    np.testing.assert_allclose(refined.pose.t, truth.t, atol=1e-6)
    np.testing.assert_allclose(refined.pose.R @ refined.pose.R.T, np.eye(3), atol=1e-12)


def test_refine_pose_is_the_pose_of_nonlinear_pnp_without_its_error_summary():
    scene = make_scene(num_points=100, noise_px=0.5, seed=5)
    points, uv, _ = correspondences(scene, 1)
    start = CameraPose(R=rotation_about_axis(np.array([0.0, 1.0, 1.0]), 0.03) @ scene.poses[1].R,
                       t=scene.poses[1].t - 0.05)
    pose, refinement = refine_pose(scene.K, points, uv, start), pnp_nonlinear(scene.K, points, uv, start)
    np.testing.assert_array_equal(pose.R, refinement.pose.R)
    np.testing.assert_array_equal(pose.t, refinement.pose.t)
    with pytest.raises(DegenerateConfigurationError):
        refine_pose(scene.K, points[:5], uv[:5], start)


def one_pose_observations(pose: CameraPose, uv: np.ndarray) -> Observations:
    """Point n seen at uv[n] by the one camera `pose`."""
    n = len(uv)
    return Observations(R=np.broadcast_to(pose.R, (n, 3, 3)), t=np.broadcast_to(pose.t, (n, 3)), uv=uv,
                        point_index=np.arange(n), num_points=n)


def test_reprojection_errors_are_infinite_behind_the_camera():
    pose = CameraPose(R=np.eye(3), t=np.zeros(3))
    errors = reprojection_errors(np.eye(3), one_pose_observations(pose, np.zeros((2, 2))),
                                 np.array([[0.0, 0, 2], [0.0, 0, -2]]))
    assert errors[0] == 0.0
    assert errors[1] == np.inf


def test_the_errors_per_hypothesis_score_every_hypothesis_like_the_reprojection_error_of_its_pose():
    scene = make_scene(num_points=50, noise_px=0.5, seed=7)
    points, uv, _ = correspondences(scene, 1)
    poses = [scene.poses[1], scene.poses[2]]
    P = np.array([np.concatenate([pose.R, pose.t[:, None]], axis=1) for pose in poses])
    errors = reprojection_errors_per_hypothesis(scene.K, P, points, uv)
    assert errors.shape == (2, len(points))
    for pose, row in zip(poses, errors, strict=True):
        np.testing.assert_allclose(row, reprojection_errors(scene.K, one_pose_observations(pose, uv), points),
                                   rtol=1e-12)
    behind = reprojection_errors_per_hypothesis(np.eye(3), np.eye(3, 4)[None], np.array([[0.0, 0, -2]]),
                                                np.zeros((1, 2)))
    assert behind[0, 0] == np.inf


def turned(pose: CameraPose, axis: np.ndarray, degrees: float, centroid: np.ndarray) -> CameraPose:
    """`pose` turned about its camera axis around `centroid`, which stays where the camera sees it."""
    R = rotation_about_axis(axis, np.radians(degrees)) @ pose.R
    return CameraPose(R=R, t=pose.R @ centroid + pose.t - R @ centroid)


def test_a_pose_one_turn_from_the_truth_gives_way_to_the_truths_consensus():
    scene = make_scene(num_points=120, noise_px=0.5, seed=4)
    points, uv, _ = correspondences(scene, 1)
    truth = scene.poses[1]
    off = turned(truth, np.array([0.0, 1.0, 0.0]), 6.0, points.mean(axis=0))   # 8 of 120 inliers left
    start_inliers = (reprojection_errors_per_hypothesis(
        scene.K, np.column_stack([off.R, off.t]), points, uv) < 2.0).sum()
    best = consensus_from_turned_starts(scene.K, points, uv, off, 2.0, turn_deg=10.0, min_gain=0.05)
    assert 6 <= start_inliers < 0.5 * len(uv)
    assert rotation_angle_deg(best.pose.R, truth.R) < 0.2
    assert best.inlier_mask.sum() > 0.95 * len(uv)


def test_the_true_pose_keeps_its_place_and_turn_zero_changes_nothing():
    scene = make_scene(num_points=120, noise_px=0.5, seed=4)
    points, uv, _ = correspondences(scene, 1)
    pose = refine_pose(scene.K, points, uv, scene.poses[1])
    best = consensus_from_turned_starts(scene.K, points, uv, pose, 2.0, turn_deg=10.0, min_gain=0.05)
    assert best.pose is pose
    off = turned(pose, np.array([1.0, 0.0, 0.0]), 9.0, points.mean(axis=0))
    unturned = consensus_from_turned_starts(scene.K, points, uv, off, 2.0, turn_deg=0.0, min_gain=0.05)
    assert unturned.pose is off
