"""The initial pair's relative pose: E estimated again at a tight threshold on the verified inliers."""

import numpy as np

from estimation.config import ReconstructionConfig
from estimation.geometry.alignment import relative_pose, rotation_angle_deg
from estimation.geometry.linalg import skew
from estimation.mapper.initial_pair import tight_essential
from estimation.synthetic import look_at, project, rotation_about_axis
from estimation.two_view.essential import choose_relative_pose, fundamental_from_essential, ransac_essential
from estimation.types import CameraPose

FOCAL, SIZE = 277.0, 200
K = np.array([[FOCAL, 0.0, SIZE / 2], [0.0, FOCAL, SIZE / 2], [0.0, 0.0, 1.0]])
UP = np.array([0.0, -1.0, 0.0])


def small_image_pair(num_tight: int, num_loose: int, seed: int):
    """Two 200x200 views (focal 277 px, lego's) 8 deg apart around an object 4 units away: `num_tight`
    matches within 0.3 px of the true epipolar geometry and `num_loose` moved 2.5-4.5 px across their
    epipolar lines in the second image (Sampson distances ~1.8-3.2 px: inside verification's 4 px).
    Returns uv1, uv2 and the second camera's relative pose."""
    rng = np.random.default_rng(seed)
    centers = [4.0 * np.array([np.sin(a), 0.0, -np.cos(a)]) for a in np.radians([0.0, 8.0])]
    poses = [CameraPose.from_center(look_at(c, np.zeros(3), UP), c) for c in centers]
    points = rng.uniform(-0.8, 0.8, (num_tight + num_loose, 3))
    uv1, uv2 = (project(K, pose, points) + rng.normal(0, 0.3, (len(points), 2)) for pose in poses)
    relative = relative_pose(poses[0], poses[1])
    F = fundamental_from_essential(skew(relative.t) @ relative.R, K, K)
    lines = (F @ np.column_stack([uv1, np.ones(len(uv1))]).T).T
    normals = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    loose = np.arange(num_tight, len(points))
    offsets = rng.uniform(2.5, 4.5, len(loose)) * rng.choice([-1, 1], len(loose))
    uv2[loose] += normals[loose] * offsets[:, None]
    return uv1, uv2, relative


def rotated_essential(relative: CameraPose, degrees: float) -> np.ndarray:
    """E of the relative pose with its rotation turned by `degrees` about the vertical (a wrong E)."""
    R = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(degrees)) @ relative.R
    return skew(relative.t) @ R


def rotation_error_deg(E: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, truth: CameraPose) -> float:
    return rotation_angle_deg(choose_relative_pose(E, K, uv1, uv2).pose.R, truth.R)


def test_the_pose_comes_from_the_matches_that_fit_it_tightly():
    """On small images a 4 px threshold lets several essential matrices explain every match: the pose of
    the E found again at initial_pair_max_error_px is better (median over pairs and RANSAC seeds)."""
    errors_4px, errors_tight = [], []
    for scene_seed in range(10):
        uv1, uv2, truth = small_image_pair(num_tight=70, num_loose=30, seed=scene_seed)
        for ransac_seed in range(2):
            config = ReconstructionConfig(ransac={"seed": ransac_seed})
            verified = ransac_essential(uv1, uv2, K, K, 4.0, config.ransac).E
            errors_4px.append(rotation_error_deg(verified, uv1, uv2, truth))
            errors_tight.append(rotation_error_deg(tight_essential(K, verified, uv1, uv2, config), uv1, uv2,
                                                   truth))
    assert np.median(errors_tight) < 0.5 * np.median(errors_4px)


def test_too_few_tight_matches_keep_the_verified_essential_matrix():
    config = ReconstructionConfig()
    uv1, uv2, truth = small_image_pair(config.mapper.min_initial_pair_inliers - 5, num_loose=40, seed=0)
    verified = rotated_essential(truth, 4.0)
    np.testing.assert_array_equal(tight_essential(K, verified, uv1, uv2, config), verified)
