"""Look-alike pairs: verified pairs whose relative rotation contradicts the rest of the view graph.

From one viewpoint, the far side of a symmetric object looks like its near side from the opposite viewpoint.
The pair of those two views verifies (its matches fit an E), but its relative rotation is the look-alike's,
up to a half turn from the truth, and in the tracks its matches would join the two sides into one: a model
folded onto itself. A look-alike shares only the symmetric part of its views, so each image's true
neighbours have more inliers than its look-alikes: the world rotations are averaged over each image's
strongest pairs (`TwoViewConfig.anchor_pairs_per_image`), and a pair of views that they put on different
sides (over LOOK_ALIKE_MIN_APART_DEG apart) whose own rotation is more than `max_rotation_residual_deg` from
them is a look-alike, left out of the tracks. The limit is wide because the E of a small object seen from
afar may trade rotation for translation by tens of degrees (lego_200: up to ~60 deg), while a look-alike is
off by about a half turn; a pair of views on one side is kept whatever its E says (its matches agree).

Where some image's strongest pairs contradict each other (a sparse ring whose look-alikes are as strong as
its neighbours), nothing is left out: a ring folded onto itself is as consistent as the true one but for
the link that closes it, so the rotations cannot tell. The alternatives, the look-alikes of the rotations
that keep the contradicted pairs and those of the rotations that contradict them, are left to the mapping
to try (`pipeline.with_alternatives`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from estimation.config import TwoViewConfig
from estimation.geometry.rotation_averaging import (
    refined_rotations,
    relative_residuals_deg,
    spanning_tree_rotations,
)
from estimation.two_view.essential import project_to_essential, relative_rotations, to_normalized
from estimation.two_view.geometry import TwoViewGeometry

AVERAGING_SCALE_DEG = 5.0
"""Cauchy scale of the rotation averaging: pairs this far from the average count half."""
AVERAGING_SWEEPS = 20
"""Jacobi sweeps of the averaging after the spanning tree."""
LOOK_ALIKE_MIN_APART_DEG = 90.0
"""A look-alike pairs views at least this far apart in the averaged rotations (different sides)."""
CHIRALITY_POINTS = 32
"""This many of a pair's inliers (evenly picked) decide which of E's four poses it has."""
ADOPTED_MAX_DEG = 45.0
"""A model that puts a look-alike pair's views within this of the pair's own rotation has adopted it (its
far side folded onto the near one); a model in place puts them about a half turn from it."""
ADOPTED_MIN_SHARE = 0.5
"""A folded model adopts most of the look-alikes between its registered images (rendered boxes: 6 and 7 of 8
by their 9th image, 47 of 74 at the end); one in place only those that the averaged rotations of a poorly
linked image made look-alikes (lego_200 without calibration: 2 of 12)."""


class PairRotations(NamedTuple):
    """The verified pairs' relative rotations: R_j = R_ij R_i (world-to-camera)."""

    pairs: np.ndarray        # (P, 2) (i, j), i < j
    R_relative: np.ndarray   # (P, 3, 3)
    inliers: np.ndarray      # (P,) the pair's verified inliers


class LookAlikes(NamedTuple):
    """What `look_alike_pairs` found in a view graph."""

    pairs: list[tuple[int, int]]       # the pairs left out
    residual_deg: np.ndarray           # (P,) of every pair of the PairRotations: angle(R_ij, R_j R_i^T)
    conflicts: list[tuple[int, int]]   # strongest pairs of their images that are as far: no pair left out
    # With conflicts, pairs to leave out instead, in order: the look-alikes of the rotations that keep the
    # conflicting pairs, then those of the rotations averaged over every strongest pair, which contradict
    # them (the pipeline maps with every pair and with each set left out: `with_alternatives`).
    alternatives: tuple[tuple[tuple[int, int], ...], ...] = ()


NO_LOOK_ALIKES = LookAlikes([], np.zeros(0), [])
"""What a view graph without a check (no intrinsics, or no limit) gives."""


def pair_rotations(geometries: dict[tuple[int, int], TwoViewGeometry],
                   inlier_uv: Callable[[int, int], tuple], K: np.ndarray, min_inliers: int) -> PairRotations:
    """R_ij of each pair with E (or F: E = K^T F K) and min_inliers or more, from the pose putting most of
    CHIRALITY_POINTS of its inliers in front of both cameras (`relative_rotations`). inlier_uv(i, j): the
    pixels of the pair's inliers in i and in j; K: the images' calibration."""
    pairs = [pair for pair, geometry in geometries.items()
             if (geometry.E is not None or geometry.F is not None) and geometry.num_inliers >= min_inliers]
    E = np.zeros((len(pairs), 3, 3))
    x_i, x_j = np.zeros((2, len(pairs), CHIRALITY_POINTS, 2))
    for k, (i, j) in enumerate(pairs):
        geometry = geometries[(i, j)]
        E[k] = geometry.E if geometry.E is not None else project_to_essential(K.T @ geometry.F @ K)
        uv_i, uv_j = inlier_uv(i, j)
        # Evenly spread picks, repeated where the pair has fewer inliers (a repeat only counts twice).
        picked = np.linspace(0, len(uv_i) - 1, CHIRALITY_POINTS).astype(int)
        x_i[k], x_j[k] = to_normalized(K, uv_i[picked]), to_normalized(K, uv_j[picked])
    return PairRotations(np.array(pairs, int).reshape(-1, 2), relative_rotations(E, x_i, x_j),
                         np.array([geometries[pair].num_inliers for pair in pairs], float))


def look_alikes_under(K: np.ndarray, geometries: dict[tuple[int, int], TwoViewGeometry],
                      inlier_uv: Callable[[int, int], tuple], num_images: int, config: TwoViewConfig
                      ) -> tuple[PairRotations, LookAlikes]:
    """The verified pairs' rotations under the calibration K (`pair_rotations`) and the look-alikes among
    them (`look_alike_pairs`)."""
    rotations = pair_rotations(geometries, inlier_uv, K, config.min_inliers)
    return rotations, look_alike_pairs(num_images, rotations, config)


def strongest_pairs(pairs: np.ndarray, inliers: np.ndarray, per_image: int) -> np.ndarray:
    """(P,) bool: the pair is among the per_image pairs with the most inliers of either of its images."""
    image = pairs.ravel()
    pair = np.repeat(np.arange(len(pairs)), 2)
    order = np.lexsort((pair, -inliers[pair], image))        # by image, most inliers first
    image, pair = image[order], pair[order]
    starts = np.flatnonzero(np.r_[True, image[1:] != image[:-1]])
    rank = np.arange(len(image)) - np.repeat(starts, np.diff(np.r_[starts, len(image)]))
    strongest = np.zeros(len(pairs), bool)
    strongest[pair[rank < per_image]] = True
    return strongest


def averaged_rotations(num_images: int, rotations: PairRotations, anchor: np.ndarray, first: np.ndarray
                       ) -> np.ndarray:
    """World rotations averaged (Cauchy at AVERAGING_SCALE_DEG) over the `anchor` pairs and the spanning tree
    of the most inliers that starts them: the tree takes the `first` pairs (P,) bool, then the other anchors,
    then the rest (their inliers raised above every other pair's)."""
    top = rotations.inliers.max()
    tree = spanning_tree_rotations(num_images, rotations.pairs, rotations.R_relative,
                                   rotations.inliers + top * (anchor.astype(float) + first))
    used = anchor | tree.in_tree
    return refined_rotations(tree.rotations, rotations.pairs[used], rotations.R_relative[used],
                             rotations.inliers[used], AVERAGING_SCALE_DEG, AVERAGING_SWEEPS)


def far_side_pairs(averaged: np.ndarray, rotations: PairRotations, far: np.ndarray) -> list[tuple[int, int]]:
    """The `far` pairs (P,) bool that the averaged rotations put over LOOK_ALIKE_MIN_APART_DEG apart: a
    look-alike joins views of different sides; a pair of views on one side is kept whatever its E says (its
    matches agree, only its E traded rotation for translation)."""
    apart_deg = relative_residuals_deg(averaged, rotations.pairs, np.eye(3))
    return [tuple(pair) for pair in rotations.pairs[far & (apart_deg > LOOK_ALIKE_MIN_APART_DEG)].tolist()]


def look_alike_pairs(num_images: int, rotations: PairRotations, config: TwoViewConfig) -> LookAlikes:
    """The pairs of views over LOOK_ALIKE_MIN_APART_DEG apart and more than config.max_rotation_residual_deg
    from the rotations averaged over each image's config.anchor_pairs_per_image strongest pairs (and the
    spanning tree that starts them); none when some of those strongest pairs are that far themselves
    (`LookAlikes.conflicts`), but then the look-alikes of the rotations that keep them and of those that do
    not (`LookAlikes.alternatives`)."""
    if len(rotations.pairs) == 0 or config.max_rotation_residual_deg is None:
        return NO_LOOK_ALIKES
    limit = config.max_rotation_residual_deg
    anchor = strongest_pairs(rotations.pairs, rotations.inliers, config.anchor_pairs_per_image)
    averaged = averaged_rotations(num_images, rotations, anchor, np.zeros(len(anchor), bool))
    residual = relative_residuals_deg(averaged, rotations.pairs, rotations.R_relative)
    conflicts = (residual > limit) & anchor
    if not conflicts.any():
        return LookAlikes(far_side_pairs(averaged, rotations, residual > limit), residual, [])
    # Some image's strongest pairs contradict each other: its look-alikes are as strong as its true
    # neighbours (a sparse ring). The tree took the strongest, so a look-alike may have won over the weaker
    # link that closes the ring; the rotations that keep that link contradict the look-alikes instead.
    # Which of the two is right the rotations cannot tell (a fold is as consistent): the mapping decides.
    kept = averaged_rotations(num_images, rotations, anchor, conflicts)
    kept_residual = relative_residuals_deg(kept, rotations.pairs, rotations.R_relative)
    return LookAlikes([], residual, [tuple(pair) for pair in rotations.pairs[conflicts].tolist()],
                      (tuple(far_side_pairs(kept, rotations, kept_residual > limit)),
                       tuple(far_side_pairs(averaged, rotations, residual > limit))))


def registered_pairs(pairs: list[tuple[int, int]], world_rotations: np.ndarray) -> list[tuple[int, int]]:
    """The `pairs` whose two images have a rotation (N, 3, 3; NaN where not registered)."""
    registered = np.isfinite(world_rotations[:, 0, 0])
    return [(i, j) for i, j in pairs if registered[i] and registered[j]]


def is_adopted(rotations: PairRotations, pairs: list[tuple[int, int]], world_rotations: np.ndarray,
               min_adopted: int) -> bool:
    """min_adopted or more of the look-alike `pairs` adopted (`adopted_pairs`), and at least
    ADOPTED_MIN_SHARE of those between registered images: a model folded onto itself."""
    adopted = len(adopted_pairs(rotations, pairs, world_rotations))
    between = len(registered_pairs(pairs, world_rotations))
    return adopted >= min_adopted and adopted >= ADOPTED_MIN_SHARE * between


def adopted_pairs(rotations: PairRotations, pairs: list[tuple[int, int]], world_rotations: np.ndarray
                  ) -> list[tuple[int, int]]:
    """The `pairs` (look-alikes) whose own rotation R_ij a model's world-to-camera rotations (N, 3, 3; NaN
    where not registered) reproduce within ADOPTED_MAX_DEG: angle(R_ij, R_j R_i^T)."""
    chosen = set(pairs)
    index = np.array([k for k, pair in enumerate(rotations.pairs.tolist()) if tuple(pair) in chosen], int)
    residual = relative_residuals_deg(world_rotations, rotations.pairs[index], rotations.R_relative[index])
    return [tuple(pair) for pair in rotations.pairs[index[residual < ADOPTED_MAX_DEG]].tolist()]
