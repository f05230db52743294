"""Rotation averaging over a view graph, against known world rotations: the spanning tree chains exact
relative rotations, the reweighted averaging keeps noisy ones near the truth and leaves wrong ones with
their error as residual."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.geometry.alignment import rotation_angles_deg
from estimation.geometry.rotation_averaging import (
    anchors,
    nearest_rotations,
    refined_rotations,
    relative_residuals_deg,
    spanning_tree_rotations,
)

HALF_TURN = Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix()


def ring_graph(num_images: int, noise_deg: float, seed: int, wrong_every: int = 0):
    """World rotations, ring pairs (i, i+1), (i, i+2) with noisy relative rotations and 100 inliers each,
    and with wrong_every > 0, pairs (i, i + N/2) every wrong_every images, a half turn off, 40 inliers."""
    rng = np.random.default_rng(seed)
    world = Rotation.random(num_images, random_state=seed).as_matrix()
    pairs = [(i, (i + step) % num_images) for i in range(num_images) for step in (1, 2)]
    wrong = [(i, (i + num_images // 2) % num_images) for i in range(0, num_images, wrong_every or num_images)]
    if not wrong_every:
        wrong = []
    pairs = np.array(pairs + wrong)
    noise = Rotation.from_rotvec(rng.normal(size=(len(pairs), 3)) * np.radians(noise_deg) / np.sqrt(3))
    R_relative = noise.as_matrix() @ world[pairs[:, 1]] @ world[pairs[:, 0]].swapaxes(1, 2)
    R_relative[len(pairs) - len(wrong):] = HALF_TURN @ R_relative[len(pairs) - len(wrong):]
    weights = np.r_[np.full(len(pairs) - len(wrong), 100.0), np.full(len(wrong), 40.0)]
    return world, pairs, R_relative, weights, len(pairs) - len(wrong)


def errors_up_to_a_global_rotation_deg(rotations, world):
    """angle(R_i R_0^T, W_i W_0^T): the rotations' error once their frame is the truth's."""
    return rotation_angles_deg(rotations @ rotations[0].T, world @ world[0].T)


def test_the_spanning_tree_chains_exact_relative_rotations_into_the_world_rotations():
    world, pairs, R_relative, weights, _ = ring_graph(10, noise_deg=0.0, seed=1)
    tree = spanning_tree_rotations(10, pairs, R_relative, weights)
    assert tree.in_tree.sum() == 9
    assert errors_up_to_a_global_rotation_deg(tree.rotations, world).max() < 1e-6
    assert relative_residuals_deg(tree.rotations, pairs, R_relative).max() < 1e-6


def test_each_connected_part_is_anchored_at_its_heaviest_image_and_an_image_without_pairs_stays_unknown():
    _, pairs, R_relative, weights, _ = ring_graph(6, noise_deg=0.0, seed=2)
    pairs = np.concatenate([pairs, pairs + 6])          # a second ring of images 6..11; image 12 alone
    weights = np.concatenate([weights, weights])
    weights[pairs[:, 0] == 8] += 1.0                     # image 8 the heaviest of the second ring
    R_relative = np.concatenate([R_relative, R_relative])
    assert sorted(anchors(13, pairs, weights).tolist())[1] == 8
    rotations = spanning_tree_rotations(13, pairs, R_relative, weights).rotations
    np.testing.assert_allclose(rotations[8], np.eye(3))
    assert np.isnan(rotations[12]).all() and not np.isnan(rotations[:12]).any()


def test_the_nearest_rotation_of_a_rotation_is_itself_and_of_a_scaled_noisy_one_a_proper_rotation():
    R = Rotation.random(5, random_state=3).as_matrix()
    np.testing.assert_allclose(nearest_rotations(R), R, atol=1e-12)
    near = nearest_rotations(2.0 * R + 0.05 * np.random.default_rng(3).normal(size=R.shape))
    np.testing.assert_allclose(near @ near.swapaxes(1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(near), 1.0)
    assert rotation_angles_deg(near, R).max() < 5.0


def test_averaging_noisy_pairs_with_a_few_half_turned_ones_keeps_the_truth_and_the_half_turns_stand_out():
    world, pairs, R_relative, weights, num_right = ring_graph(24, noise_deg=2.0, seed=4, wrong_every=3)
    tree = spanning_tree_rotations(24, pairs, R_relative, weights)
    averaged = refined_rotations(tree.rotations, pairs, R_relative, weights, scale_deg=5.0, iterations=20)
    error = errors_up_to_a_global_rotation_deg(averaged, world)
    assert error.max() < 5.0
    assert error.mean() < 0.75 * errors_up_to_a_global_rotation_deg(tree.rotations, world).mean()
    residual = relative_residuals_deg(averaged, pairs, R_relative)
    assert residual[:num_right].max() < 6.0
    assert residual[num_right:].min() > 170.0


@pytest.mark.parametrize("iterations", [0, 20])
def test_averaging_exact_relative_rotations_leaves_them_exact(iterations):
    world, pairs, R_relative, weights, _ = ring_graph(8, noise_deg=0.0, seed=5)
    tree = spanning_tree_rotations(8, pairs, R_relative, weights)
    averaged = refined_rotations(tree.rotations, pairs, R_relative, weights, 5.0, iterations)
    assert errors_up_to_a_global_rotation_deg(averaged, world).max() < 1e-6
