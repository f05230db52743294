"""The visibility pyramid score: more points and points spread over the image score higher; it counts
the occupied cells of every level exactly (one sort of Z-order codes serves all levels)."""

import numpy as np

from estimation.mapper.next_image import PYRAMID_LEVELS, pyramid_cells, visibility_pyramid_scores, z_order


def test_spread_points_outscore_as_many_clustered_points():
    rng = np.random.default_rng(0)
    spread = rng.uniform([0, 0], [640, 480], (100, 2))
    clustered = rng.uniform([0, 0], [60, 40], (100, 2))
    uv = np.concatenate([spread, clustered])
    scores = visibility_pyramid_scores(pyramid_cells(np.repeat([0, 1], 100), uv, 640, 480), 3)
    assert scores[0] > 2 * scores[1] > 0
    assert scores[2] == 0                                  # no visible point, no score
    assert not visibility_pyramid_scores(pyramid_cells(np.zeros(2, int), uv[:2], 640, 480), 3,
                                         np.zeros(2, bool)).any()


def test_one_point_scores_one_cell_per_level_and_a_full_grid_scores_the_maximum():
    one = visibility_pyramid_scores(pyramid_cells(np.array([0]), np.array([[10.0, 10.0]]), 640, 480), 1)
    assert one[0] == sum(4**level for level in range(1, PYRAMID_LEVELS + 1))
    dim = 2**PYRAMID_LEVELS
    centres = (np.stack(np.meshgrid(np.arange(dim), np.arange(dim)), axis=-1).reshape(-1, 2) + 0.5) / dim
    full = visibility_pyramid_scores(pyramid_cells(np.zeros(dim * dim, int), centres * [640, 480], 640, 480),
                                     1)
    assert full[0] == sum(16**level for level in range(1, PYRAMID_LEVELS + 1))


def test_z_order_interleaves_the_bits_so_that_a_shift_gives_the_coarser_cell():
    assert z_order(np.array([0b101]), np.array([0b011]), 3)[0] == 0b011011   # y2 x2 y1 x1 y0 x0
    x, y = np.meshgrid(np.arange(16), np.arange(16))
    code = z_order(x.ravel(), y.ravel(), 4)
    assert sorted(code) == list(range(256))                                # one code per cell
    for coarser in (1, 2, 3):
        parent = z_order(x.ravel() >> coarser, y.ravel() >> coarser, 4 - coarser)
        np.testing.assert_array_equal(code >> (2 * coarser), parent)


def test_scores_count_the_occupied_cells_of_each_level_as_the_definition():
    rng = np.random.default_rng(1)
    image_index = rng.integers(0, 5, 400)
    uv = np.concatenate([rng.uniform([0, 0], [640, 480], (300, 2)),      # spread, and clustered
                         rng.uniform([300, 200], [320, 215], (100, 2))])
    expected = np.zeros(6)
    for level in range(1, PYRAMID_LEVELS + 1):
        dim = 2**level
        cells = np.floor(uv / [640, 480] * dim).astype(int)
        for m in range(6):
            expected[m] += dim * dim * len({tuple(c) for c in cells[image_index == m]})
    cells = pyramid_cells(image_index, uv, 640, 480)
    np.testing.assert_array_equal(visibility_pyramid_scores(cells, 6), expected)
    # The scores of a subset of the points are those of their own cells.
    visible = rng.random(400) < 0.5
    np.testing.assert_array_equal(visibility_pyramid_scores(cells, 6, visible),
                                  visibility_pyramid_scores(pyramid_cells(image_index[visible], uv[visible],
                                                                          640, 480), 6))
