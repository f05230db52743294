"""The RANSAC driver on lines and planes with outliers: consensus, adaptive iterations, LO refits."""

import numpy as np
import pytest

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.linalg import null_vector
from estimation.geometry.ransac import (
    HYPOTHESES_PER_BATCH,
    PREVERIFICATION_POINTS,
    ransac,
    required_iterations,
)


def hyperplane_through(points: np.ndarray) -> np.ndarray:
    """(..., s, d) points -> (..., d + 1) unit normal n with n . [x, 1] = 0 (least squares for s > d)."""
    homogeneous = np.concatenate([points, np.ones((*points.shape[:-1], 1))], axis=-1)
    return null_vector(homogeneous)


def distances(models: np.ndarray, points: np.ndarray) -> np.ndarray:
    """|n . [x, 1]| / ||n[:d]||: Euclidean point-to-hyperplane distance, (M, N)."""
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    return np.abs(models @ homogeneous.T) / np.linalg.norm(models[:, :-1], axis=1, keepdims=True)


def noisy_hyperplane(num: int, dim: int, outlier_fraction: float, seed: int):
    """Points within +-0.01 of the hyperplane x_last = 0.5 x_0 + 0.2 (+ 0.3 x_1); outliers 0.1 to 3 off it."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (num, dim))
    slope = np.array([0.5, 0.3][: dim - 1])
    points[:, -1] = points[:, :-1] @ slope + 0.2 + rng.uniform(-0.01, 0.01, num)
    outlier = rng.random(num) < outlier_fraction
    points[outlier, -1] += rng.choice([-1.0, 1.0], outlier.sum()) * rng.uniform(0.1, 3.0, outlier.sum())
    return points, ~outlier, np.concatenate([slope, [-1.0], [0.2]])


def fit(points, config=RansacConfig(), refit=True):
    return ransac((points,), hyperplane_through, points.shape[1], distances, 0.02, config,
                  refit=(lambda inliers: hyperplane_through(inliers)[None]) if refit else None,
                  model_name="hyperplane")


@pytest.mark.parametrize("dim", [2, 3])
def test_a_line_and_a_plane_are_found_among_40_percent_outliers(dim):
    points, inlier, truth = noisy_hyperplane(500, dim, 0.4, seed=dim)
    result = fit(points)
    np.testing.assert_array_equal(result.inlier_mask, inlier)
    model = result.model * np.sign(result.model[-1] / truth[-1])
    np.testing.assert_allclose(model / np.linalg.norm(model), truth / np.linalg.norm(truth), atol=0.01)
    np.testing.assert_allclose(result.residuals, distances(result.model[None], points)[0])


def test_iterations_adapt_to_the_inlier_ratio_within_the_configured_bounds():
    clean, _, _ = noisy_hyperplane(300, 3, 0.0, seed=0)
    dirty, _, _ = noisy_hyperplane(300, 3, 0.7, seed=0)
    assert fit(clean).iterations == HYPOTHESES_PER_BATCH
    assert fit(clean, RansacConfig(min_iterations=500)).iterations >= 500
    # w = 0.3, s = 3: log(0.001) / log(1 - 0.027) = 252 samples at least.
    assert fit(dirty).iterations >= required_iterations(0.3, 3, 0.999, 5000)
    assert fit(dirty, RansacConfig(max_iterations=HYPOTHESES_PER_BATCH)).iterations == HYPOTHESES_PER_BATCH


def test_local_optimization_never_shrinks_the_consensus():
    points, inlier, _ = noisy_hyperplane(400, 3, 0.5, seed=5)
    config = RansacConfig(max_iterations=HYPOTHESES_PER_BATCH, min_iterations=HYPOTHESES_PER_BATCH)
    plain = fit(points, config.model_copy(update={"local_refits": 0}))
    refined = fit(points, config)
    assert refined.inlier_mask.sum() >= plain.inlier_mask.sum()
    assert (refined.inlier_mask == inlier).mean() > 0.99


def test_a_solver_with_several_roots_is_scored_root_by_root():
    points, inlier, _ = noisy_hyperplane(200, 2, 0.3, seed=7)

    def with_a_decoy(sample):                     # each sample gives its line and a useless one
        lines = hyperplane_through(sample)
        return np.concatenate([lines, np.tile([0.0, 1.0, -10.0], (len(lines), 1))])

    result = ransac((points,), with_a_decoy, 2, distances, 0.02, RansacConfig())
    np.testing.assert_array_equal(result.inlier_mask, inlier)


def test_too_few_rows_or_no_consensus_is_degenerate():
    with pytest.raises(DegenerateConfigurationError, match="hyperplane needs at least 3 .* got 2"):
        fit(np.zeros((2, 3)))
    scattered = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    with pytest.raises(DegenerateConfigurationError, match="no hyperplane with 3\\+ inliers among 50"):
        ransac((scattered,), hyperplane_through, 3, distances, 0.0, RansacConfig(max_iterations=64),
               model_name="hyperplane")


def test_required_iterations_follows_the_formula():
    # log(1 - 0.99) / log(1 - 0.5^8) = 1176.6
    assert required_iterations(0.5, 8, 0.99, 10_000) == 1177
    assert required_iterations(1.0, 8, 0.99, 10_000) == 1
    assert required_iterations(0.0, 8, 0.99, 500) == 500
    assert required_iterations(0.1, 8, 0.99, 500) == 500


@pytest.mark.parametrize("num", [PREVERIFICATION_POINTS - 10, 4 * PREVERIFICATION_POINTS])
def test_hypotheses_are_pre_verified_on_a_subset_only_when_there_are_more_rows_than_it(num):
    points, inlier, _ = noisy_hyperplane(num, 2, 0.3, seed=5)
    rows_scored = []

    def recorded(models, rows):
        rows_scored.append(len(rows))
        return distances(models, rows)

    result = ransac((points,), hyperplane_through, 2, recorded, 0.02, RansacConfig())
    np.testing.assert_array_equal(result.inlier_mask, inlier)
    assert set(rows_scored) == ({num} if num <= PREVERIFICATION_POINTS else {num, PREVERIFICATION_POINTS})
