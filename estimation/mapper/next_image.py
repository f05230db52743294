"""Which image to register next: the number and spread of its visible triangulated points.

COLMAP's visibility pyramid (Schoenberger & Frahm 2016, sec. 4.2): level l = 1..L splits the image into
a 2^l x 2^l grid; every occupied cell adds (2^l)^2 to the score. Many points score high, and points spread
over the whole image score higher than as many points in one corner, which makes the PnP well conditioned.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

PYRAMID_LEVELS = 6
"""COLMAP's default number of levels (64 x 64 cells at the finest)."""


def z_order(x: np.ndarray, y: np.ndarray, bits: int) -> np.ndarray:
    """Morton code: bit b of x at bit 2b, bit b of y at bit 2b + 1 (x, y < 2^bits), so that the cell of
    the grid 2^k times coarser is code >> 2k."""
    code = np.zeros_like(x)
    for bit in range(bits):
        code |= ((x >> bit) & 1) << (2 * bit) | ((y >> bit) & 1) << (2 * bit + 1)
    return code


class PyramidCells(NamedTuple):
    """Observations' cells in the finest grid as sorted (image, Z-order code) keys."""

    keys: np.ndarray   # (O,) sorted image << 2 levels | z_order(cell x, cell y)
    order: np.ndarray  # (O,) the observation of each key
    levels: int


def pyramid_cells(image_index: np.ndarray, uv: np.ndarray, width: float, height: float,
                  levels: int = PYRAMID_LEVELS) -> PyramidCells:
    """The finest cell of each point uv (O, 2) seen in image image_index (O,), as sorted keys: computed
    once, they serve every later scoring (a masked subset of sorted keys is still sorted)."""
    relative = np.clip(np.asarray(uv, float) / [width, height], 0.0, 1.0 - 1e-9)
    cell = np.floor(relative * (1 << levels)).astype(np.int64)
    keys = (np.asarray(image_index, np.int64) << (2 * levels)) | z_order(cell[:, 0], cell[:, 1], levels)
    order = np.argsort(keys, kind="stable")
    return PyramidCells(keys=keys[order], order=order, levels=levels)


def visibility_pyramid_scores(cells: PyramidCells, num_images: int, visible: np.ndarray | None = None
                              ) -> np.ndarray:
    """score_m = sum_{l=1..L} (2^l)^2 #{occupied cells of the 2^l x 2^l grid} for the points of image m
    among `cells`, only those marked in visible (O,) bool when given; (num_images,) float.

    The key prefix key >> 2 (L - l) is the cell of level l, and it keeps each level's cells sorted too."""
    keys = cells.keys if visible is None else cells.keys[visible[cells.order]]
    levels = cells.levels
    scores = np.zeros(num_images)
    for level in range(1, levels + 1):
        level_cells = keys >> (2 * (levels - level))
        first = np.ones(len(level_cells), bool)       # the first key of each cell
        first[1:] = level_cells[1:] != level_cells[:-1]
        scores += 4**level * np.bincount(level_cells[first] >> (2 * level), minlength=num_images)
    return scores
