"""The visibility pyramid score: more points and points spread over the image score higher."""

import numpy as np

from estimation.mapper.next_image import PYRAMID_LEVELS, visibility_pyramid_scores


def test_spread_points_outscore_as_many_clustered_points():
    rng = np.random.default_rng(0)
    spread = rng.uniform([0, 0], [640, 480], (100, 2))
    clustered = rng.uniform([0, 0], [60, 40], (100, 2))
    uv = np.concatenate([spread, clustered])
    scores = visibility_pyramid_scores(np.repeat([0, 1], 100), uv, 3, 640, 480)
    assert scores[0] > 2 * scores[1] > 0
    assert scores[2] == 0                                  # no visible point, no score


def test_one_point_scores_one_cell_per_level_and_a_full_grid_scores_the_maximum():
    one = visibility_pyramid_scores(np.array([0]), np.array([[10.0, 10.0]]), 1, 640, 480)
    assert one[0] == sum(4**level for level in range(1, PYRAMID_LEVELS + 1))
    dim = 2**PYRAMID_LEVELS
    centres = (np.stack(np.meshgrid(np.arange(dim), np.arange(dim)), axis=-1).reshape(-1, 2) + 0.5) / dim
    full = visibility_pyramid_scores(np.zeros(dim * dim, int), centres * [640, 480], 1, 640, 480)
    assert full[0] == sum(16**level for level in range(1, PYRAMID_LEVELS + 1))
