"""Which image to register next: the number and spread of its visible triangulated points.

COLMAP's visibility pyramid (Schoenberger & Frahm 2016, sec. 4.2): level l = 1..L splits the image into
a 2^l x 2^l grid; every occupied cell adds (2^l)^2 to the score. Many points score high, and points spread
over the whole image score higher than as many points in one corner, which makes the PnP well conditioned.
"""

from __future__ import annotations

import numpy as np

PYRAMID_LEVELS = 6
"""COLMAP's default number of levels (64 x 64 cells at the finest)."""


def visibility_pyramid_scores(
    image_index: np.ndarray,
    uv: np.ndarray,
    num_images: int,
    width: float,
    height: float,
    levels: int = PYRAMID_LEVELS,
) -> np.ndarray:
    """score_m = sum_{l=1..L} (2^l)^2 #{occupied cells of the 2^l x 2^l grid} for the points uv (O, 2)
    seen in image image_index (O,); (num_images,) float."""
    scores = np.zeros(num_images)
    if len(uv) == 0:
        return scores
    relative = np.clip(np.asarray(uv, float) / [width, height], 0.0, 1.0 - 1e-9)
    image_index = np.asarray(image_index, np.int64)
    for level in range(1, levels + 1):
        dim = 1 << level
        cell = np.floor(relative * dim).astype(np.int64)
        key = (image_index * dim + cell[:, 1]) * dim + cell[:, 0]
        occupied_images = np.unique(key) // (dim * dim)
        scores += dim * dim * np.bincount(occupied_images, minlength=num_images)
    return scores
