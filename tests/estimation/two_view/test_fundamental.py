"""Normalized 8-point fundamental matrix and its adaptive RANSAC, against synthetic ground truth."""

import numpy as np
import pytest

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.alignment import relative_pose
from estimation.geometry.ransac import HYPOTHESES_PER_BATCH
from estimation.synthetic import make_scene
from estimation.two_view.fundamental import (
    _enforce_rank_two,
    eight_point,
    epipolar_rows,
    hartley_normalization,
    ransac_fundamental,
    sampson_distance,
)


def true_fundamental(scene, i, j):
    """F = K^-T [t]x R K^-1 of camera j relative to camera i, unit norm."""
    rel = relative_pose(scene.poses[i], scene.poses[j])
    t = rel.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K_inv = np.linalg.inv(scene.K)
    F = K_inv.T @ tx @ rel.R @ K_inv
    return F / np.linalg.norm(F)


def same_up_to_sign(A, B):
    return min(np.abs(A - B).max(), np.abs(A + B).max())


def test_hartley_normalization_centres_points_at_mean_distance_sqrt2():
    uv = np.random.default_rng(0).uniform(0, 800, (100, 2))
    n = hartley_normalization(uv)
    np.testing.assert_allclose(n.points.mean(axis=0), 0, atol=1e-12)
    assert np.linalg.norm(n.points, axis=1).mean() == pytest.approx(np.sqrt(2))
    homogeneous = np.hstack([uv, np.ones((100, 1))]) @ n.T.T
    np.testing.assert_allclose(homogeneous[:, :2], n.points, atol=1e-12)


def svd_rank_two(F):
    """The closest rank-2 matrix by the SVD: the smallest singular value set to zero."""
    U, S, Vt = np.linalg.svd(F)
    S[..., 2] = 0.0
    return U @ (S[..., :, None] * Vt)


def test_rank_two_projection_is_the_svds_on_random_rank_two_and_ill_conditioned_matrices():
    rng = np.random.default_rng(0)
    U, _, Vt = np.linalg.svd(rng.standard_normal((4, 3, 3)))
    spectra = np.array([[1.0, 0.5, 0.0], [1.0, 0.1, 1e-9], [1.0, 1e-2, 1e-3], [1.0, 1.0, 0.3]])
    F = np.concatenate([rng.standard_normal((64, 3, 3)), U @ (spectra[..., :, None] * Vt)])
    projected = _enforce_rank_two(F)
    np.testing.assert_allclose(projected, svd_rank_two(F), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(projected), 0.0, atol=1e-12)
    np.testing.assert_allclose(_enforce_rank_two(F[0]), svd_rank_two(F[0]), atol=1e-12)


def test_eight_point_recovers_the_true_f_from_noise_free_correspondences():
    scene = make_scene(num_points=100)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 2)
    F = eight_point(uv1, uv2)
    assert same_up_to_sign(F, true_fundamental(scene, 0, 2)) < 1e-9
    assert sampson_distance(F, uv1, uv2).max() < 1e-8


def test_eight_point_works_with_exactly_eight_points_and_returns_rank_two():
    scene = make_scene(num_points=8, noise_px=1.0)
    _, uv1, uv2 = scene.tracks.pair_correspondences(0, 1)
    singular_values = np.linalg.svd(eight_point(uv1, uv2), compute_uv=False)
    assert singular_values[2] < 1e-12 * singular_values[0]
    assert singular_values[1] > 1e-6 * singular_values[0]


def test_fewer_than_eight_correspondences_are_degenerate():
    uv = np.zeros((7, 2))
    with pytest.raises(DegenerateConfigurationError, match="at least 8"):
        eight_point(uv, uv)
    with pytest.raises(DegenerateConfigurationError, match="got 7"):
        ransac_fundamental(uv, uv, RansacConfig())


def test_sampson_distance_is_the_pixel_offset_perpendicular_to_the_epipolar_line():
    # Pure horizontal translation: epipolar lines are the image rows, so the distance is |dv| / sqrt(2)
    # (Sampson spreads the offset over both images).
    F = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    uv1 = np.array([[100.0, 200.0], [300.0, 50.0]])
    uv2 = uv1 + np.array([[40.0, 0.0], [10.0, 3.0]])
    np.testing.assert_allclose(sampson_distance(F, uv1, uv2), [0.0, 3.0 / np.sqrt(2)], atol=1e-12)


def test_ransac_separates_outliers_under_noise_and_30_percent_outlier_observations():
    scene = make_scene(num_points=600, noise_px=0.5, outlier_fraction=0.3, seed=2)
    track_ids, uv1, uv2 = scene.tracks.pair_correspondences(0, 3)
    truly_inlier = scene.inlier_mask.reshape(-1, 5)[track_ids][:, [0, 3]].all(axis=1)
    result = ransac_fundamental(uv1, uv2, RansacConfig(threshold_px=1.0))
    precision = (result.inlier_mask & truly_inlier).sum() / result.inlier_mask.sum()
    recall = (result.inlier_mask & truly_inlier).sum() / truly_inlier.sum()
    assert precision > 0.97
    assert recall > 0.9
    # The estimate explains the noise-free correspondences to well under a pixel.
    clean = make_scene(num_points=600, seed=2)
    _, clean1, clean2 = clean.tracks.pair_correspondences(0, 3)
    assert np.median(sampson_distance(result.F, clean1, clean2)) < 0.2


def test_ransac_iterations_adapt_to_the_inlier_ratio():
    clean = make_scene(num_points=300, seed=3)
    dirty = make_scene(num_points=300, noise_px=0.5, outlier_fraction=0.3, seed=3)
    config = RansacConfig()
    assert ransac_fundamental(*clean.tracks.pair_correspondences(0, 1)[1:], config).iterations == (
        HYPOTHESES_PER_BATCH)
    assert ransac_fundamental(*dirty.tracks.pair_correspondences(0, 1)[1:], config).iterations > 1000


def test_epipolar_rows_dotted_with_f_are_x2t_f_x1_batched_and_single():
    rng = np.random.default_rng(5)
    F = rng.standard_normal((3, 3))
    for shape in [(40, 2), (6, 8, 2)]:
        x1, x2 = rng.standard_normal(shape), rng.standard_normal(shape)
        one = np.ones((*shape[:-1], 1))
        expected = np.einsum("...i,ij,...j->...", np.concatenate([x2, one], axis=-1), F,
                             np.concatenate([x1, one], axis=-1))
        np.testing.assert_allclose(epipolar_rows(x1, x2) @ F.ravel(), expected, atol=1e-12)
