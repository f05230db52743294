"""E by the 5-point solver (in RANSAC) or E = K^T F K, the four pose candidates and chirality, against
synthetic ground truth."""


import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.alignment import relative_pose, rotation_angle_deg
from estimation.geometry.linalg import skew
from estimation.synthetic import make_scene
from estimation.two_view.essential import (
    choose_relative_pose,
    essential_from_fundamental,
    essential_rotations,
    five_point_essential,
    in_front_of_both,
    pose_candidates,
    ransac_essential,
    refine_essential,
    relative_rotations,
    to_normalized,
)
from estimation.two_view.fundamental import eight_point, ransac_fundamental, sampson_residual
from estimation.types import CameraPose
from tests.estimation.imports import import_loads


def direction_error_deg(a, b):
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_essential_matrix_has_singular_values_one_one_zero():
    scene = make_scene(num_points=50, noise_px=1.0)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    E = essential_from_fundamental(eight_point(uv1, uv2), scene.K)
    np.testing.assert_allclose(np.linalg.svd(E, compute_uv=False), [1, 1, 0], atol=1e-12)


def test_four_candidates_are_proper_rotations_with_opposite_baselines():
    scene = make_scene(num_points=50)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    candidates = pose_candidates(essential_from_fundamental(eight_point(uv1, uv2), scene.K))
    assert len(candidates) == 4
    for pose in candidates:
        np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(pose.R) == pytest.approx(1.0)
        assert np.linalg.norm(pose.t) == pytest.approx(1.0)
    np.testing.assert_allclose(candidates[0].t, -candidates[1].t)
    assert rotation_angle_deg(candidates[0].R, candidates[2].R) > 1.0


def test_essential_rotations_of_stacked_matrices_are_each_ones_two_candidate_rotations():
    scene = make_scene(num_points=50)
    E = np.stack([essential_from_fundamental(eight_point(*scene.tracks.pair_correspondences(0, j)[1:]),
                                             scene.K) for j in (1, 2, 3)])
    rotations = essential_rotations(-2.0 * E)          # E is up to scale and sign
    assert rotations.shape == (3, 2, 3, 3)
    for one, both in zip(E, rotations, strict=True):
        for R in both:
            # E ~ [t]x R: E R^T is skew-symmetric (+-[t]x for the twisted pair), R a proper rotation
            np.testing.assert_allclose(one @ R.T, -(one @ R.T).T, atol=1e-9)
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)
        assert rotation_angle_deg(*both) > 1.0
        np.testing.assert_allclose(essential_rotations(one), both, atol=1e-12)


def test_chirality_picks_the_true_pose_from_noise_free_correspondences():
    scene = make_scene(num_points=200)
    _, uv1, uv2 = scene.tracks.pair_correspondences(1, 3)
    E = essential_from_fundamental(eight_point(uv1, uv2), scene.K)
    chosen = choose_relative_pose(E, scene.K, uv1, uv2)
    truth = relative_pose(scene.poses[1], scene.poses[3])
    assert rotation_angle_deg(chosen.pose.R, truth.R) < 1e-6
    assert direction_error_deg(chosen.pose.center, truth.center) < 1e-6
    assert chosen.in_front.all()
    assert sorted(chosen.candidate_scores) == [0, 0, 0, 200]


def test_relative_rotations_of_many_pairs_at_once_are_the_poses_chirality_picks():
    scene = make_scene(num_cameras=6, num_points=200, noise_px=0.5)
    pairs = [(0, j) for j in range(1, 6)] + [(2, 4), (5, 3)]
    E, x1, x2, truth = [], [], [], []
    for i, j in pairs:
        _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        E.append(essential_from_fundamental(eight_point(uv1, uv2), scene.K) * (-1) ** j)   # sign is free
        x1.append(to_normalized(scene.K, uv1[:32]))
        x2.append(to_normalized(scene.K, uv2[:32]))
        truth.append(relative_pose(scene.poses[i], scene.poses[j]).R)
    rotations = relative_rotations(np.stack(E), np.stack(x1), np.stack(x2))
    for R, one, true_R, (i, j) in zip(rotations, E, truth, pairs, strict=True):
        _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        np.testing.assert_allclose(R, choose_relative_pose(one, scene.K, uv1, uv2).pose.R, atol=1e-12)
        assert rotation_angle_deg(R, true_R) < 0.5


def test_relative_pose_under_noise_and_outliers_is_within_half_a_degree_and_one_percent():
    scene = make_scene(num_points=500, noise_px=0.5, outlier_fraction=0.3, seed=1)
    for i, j in [(0, 1), (0, 4), (2, 3)]:
        _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        fundamental = ransac_fundamental(uv1, uv2, RansacConfig())
        inliers = fundamental.inlier_mask
        chosen = choose_relative_pose(essential_from_fundamental(fundamental.F, scene.K), scene.K,
                                      uv1[inliers], uv2[inliers])
        truth = relative_pose(scene.poses[i], scene.poses[j])
        # Fix the unobservable scale with the true baseline length (a similarity with two cameras).
        center = chosen.pose.center * np.linalg.norm(truth.center)
        assert rotation_angle_deg(chosen.pose.R, truth.R) < 0.5
        assert np.linalg.norm(center - truth.center) < 0.01 * scene.scene_size


def test_in_front_of_both_uses_each_cameras_viewing_direction():
    # The second camera sits at z = 10 looking back along -z (rotated 180 deg about y).
    facing_back = CameraPose.from_center(np.diag([-1.0, 1.0, -1.0]), np.array([0.0, 0.0, 10.0]))
    points = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 12.0], [0.0, 0.0, -1.0], [3.0, -2.0, 9.0]])
    np.testing.assert_array_equal(in_front_of_both(facing_back, points), [True, False, False, True])


def test_no_correspondences_cannot_choose_a_pose():
    with pytest.raises(DegenerateConfigurationError):
        choose_relative_pose(np.eye(3), np.eye(3), np.zeros((0, 2)), np.zeros((0, 2)))


def true_essential(scene, i, j):
    rel = relative_pose(scene.poses[i], scene.poses[j])
    t = rel.t
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rel.R
    return E / np.linalg.norm(E)


def test_five_point_solutions_include_the_true_essential_matrix_and_satisfy_its_constraints():
    scene = make_scene(num_cameras=5, num_points=200, seed=4)
    rng = np.random.default_rng(0)
    for i, j in [(0, 1), (0, 4), (2, 3)]:
        _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        samples = np.stack([rng.choice(len(uv1), 5, replace=False) for _ in range(20)])
        x1, x2 = to_normalized(scene.K, uv1)[samples], to_normalized(scene.K, uv2)[samples]
        solutions = five_point_essential(x1, x2)
        assert 20 <= len(solutions) <= 200                       # up to ten real roots per sample
        for E in solutions:                                       # every root is an essential matrix
            np.testing.assert_allclose(2 * E @ E.T @ E - np.trace(E @ E.T) * E, 0, atol=1e-8)
        truth = true_essential(scene, i, j)
        distance = np.minimum(np.abs(solutions - truth).max(axis=(1, 2)),
                              np.abs(solutions + truth).max(axis=(1, 2)))
        assert np.sum(distance < 1e-8) >= 20                      # the truth among each sample's roots


def test_every_noise_free_sample_of_many_random_scenes_has_the_true_essential_among_its_roots():
    for seed in range(30):
        scene = make_scene(num_cameras=3, num_points=40, seed=seed)
        rng = np.random.default_rng(seed)
        for i, j in [(0, 1), (0, 2), (1, 2)]:
            _, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
            x1, x2 = to_normalized(scene.K, uv1), to_normalized(scene.K, uv2)
            truth = true_essential(scene, i, j)
            for _ in range(10):
                sample = rng.choice(len(uv1), 5, replace=False)
                solutions = five_point_essential(x1[sample][None], x2[sample][None])
                np.testing.assert_allclose(np.linalg.norm(solutions, axis=(1, 2)), 1.0)
                distance = np.minimum(np.abs(solutions - truth).max(axis=(1, 2)),
                                      np.abs(solutions + truth).max(axis=(1, 2)))
                assert distance.min() < 1e-8, (seed, i, j, sample)


def test_five_point_ransac_under_noise_and_30_percent_outliers_is_within_0_2_degrees():
    scene = make_scene(num_points=500, noise_px=0.5, outlier_fraction=0.3, seed=1)
    for i, j in [(0, 1), (0, 4), (2, 3)]:
        track_ids, uv1, uv2 = scene.tracks.pair_correspondences(i, j)
        truly_inlier = scene.inlier_mask.reshape(-1, 5)[track_ids][:, [i, j]].all(axis=1)
        result = ransac_essential(uv1, uv2, scene.K, scene.K, 1.5, RansacConfig())
        assert (result.inlier_mask & truly_inlier).sum() / result.inlier_mask.sum() > 0.97
        assert (result.inlier_mask & truly_inlier).sum() / truly_inlier.sum() > 0.9
        inliers = result.inlier_mask
        chosen = choose_relative_pose(result.E, scene.K, uv1[inliers], uv2[inliers])
        truth = relative_pose(scene.poses[i], scene.poses[j])
        assert rotation_angle_deg(chosen.pose.R, truth.R) < 0.2
        assert direction_error_deg(chosen.pose.center, truth.center) < 1.0


def test_without_the_polish_ransac_keeps_its_own_consensus_and_the_polish_does_not_lose_it():
    scene = make_scene(num_points=300, noise_px=0.5, outlier_fraction=0.3, seed=2)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    raw = ransac_essential(uv1, uv2, scene.K, scene.K, 1.5, RansacConfig(), refine=False)
    polished = ransac_essential(uv1, uv2, scene.K, scene.K, 1.5, RansacConfig())
    assert raw.iterations == polished.iterations                  # the same RANSAC, seeded alike
    assert polished.inlier_mask.sum() >= raw.inlier_mask.sum()
    np.testing.assert_array_equal(raw.inlier_mask, raw.sampson_px < 1.5)
    truth = relative_pose(scene.poses[0], scene.poses[1])
    for result in (raw, polished):
        chosen = choose_relative_pose(result.E, scene.K, uv1[result.inlier_mask], uv2[result.inlier_mask])
        assert rotation_angle_deg(chosen.pose.R, truth.R) < 0.5


def scipy_refined_essential(E, uv1, uv2, K):
    """refine_essential's problem solved by scipy's least_squares (MINPACK's LM), the reference."""
    start = pose_candidates(E)[0]
    K_inv = np.linalg.inv(K)

    def essential(params):
        t = params[3:] / np.linalg.norm(params[3:])
        return skew(t) @ Rotation.from_rotvec(params[:3]).as_matrix() @ start.R

    def residuals(params):
        return sampson_residual(K_inv.T @ essential(params) @ K_inv, uv1, uv2)

    solution = least_squares(residuals, np.concatenate([np.zeros(3), start.t]), method="lm", ftol=1e-10,
                             xtol=1e-10)
    return essential(solution.x)


def sampson_cost(E, uv1, uv2, K):
    residuals = sampson_residual(np.linalg.inv(K).T @ E @ np.linalg.inv(K), uv1, uv2)
    return residuals @ residuals


def test_refine_essential_lowers_the_sampson_cost_to_scipys_minimum():
    scene = make_scene(num_points=200, noise_px=1.0, seed=3)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    start = essential_from_fundamental(eight_point(uv1, uv2), scene.K)
    refined = refine_essential(start, uv1, uv2, scene.K, scene.K)
    reference = scipy_refined_essential(start, uv1, uv2, scene.K)
    start_cost, cost, reference_cost = (sampson_cost(E, uv1, uv2, scene.K)
                                        for E in (start, refined, reference))
    assert cost < 0.9 * start_cost
    assert reference_cost <= cost < (1 + 1e-4) * reference_cost      # stopped at ftol = 1e-4 of the minimum
    # The same pose to within a tenth of its error from the noise (0.04 deg, 0.16 deg here).
    pose, reference_pose = (choose_relative_pose(E, scene.K, uv1, uv2).pose for E in (refined, reference))
    assert rotation_angle_deg(pose.R, reference_pose.R) < 0.004
    assert direction_error_deg(pose.center, reference_pose.center) < 0.016


def test_verifying_pairs_does_not_load_scipys_optimizer():
    """Each verifying process imports two_view.geometry: scipy's optimizer (~0.2 s to import) stays out of
    every process's start."""
    assert not import_loads("estimation.two_view.geometry", "scipy.optimize")


def test_polishing_e_does_not_load_scipys_optimizer():
    """The initial pair polishes E on the mapper's clock: its 6-parameter fit runs without scipy.optimize."""
    polish = ("from estimation.synthetic import make_scene\n"
              "from estimation.config import RansacConfig\n"
              "scene = make_scene(num_points=60, noise_px=0.5)\n"
              "_, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)\n"
              "estimation.two_view.essential.ransac_essential(uv1, uv2, scene.K, scene.K, 1.5,\n"
              "                                               RansacConfig())")
    assert not import_loads("estimation.two_view.essential", "scipy.optimize", then=polish)
