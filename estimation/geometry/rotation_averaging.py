"""Rotation averaging over a view graph: world-to-camera rotations R_i from the pairs' relative rotations.

Convention: pair (i, j) carries R_ij with R_j = R_ij R_i (x_j = R_ij x_i + t_ij, world-to-camera). The
rotations start from a maximum spanning tree of the pairs' weights and are refined by iteratively
reweighted chordal averaging (Cauchy weights), so that a minority of wrong pairs pulls them little. Each
connected part of the graph gets its own frame, anchored at its heaviest image.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

from estimation.geometry.alignment import rotation_angles_deg


def _graph(num_images: int, pairs: np.ndarray, values: np.ndarray):
    return coo_matrix((values, (pairs[:, 0], pairs[:, 1])), shape=(num_images, num_images)).tocsr()


def anchors(num_images: int, pairs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The heaviest image (sum of its pairs' weights) of each connected part of the graph that has a pair."""
    _, part = connected_components(_graph(num_images, pairs, weights), directed=False)
    degree = np.bincount(pairs.ravel(), weights=np.repeat(weights, 2), minlength=num_images)
    order = np.lexsort((-degree, part))               # by part, heaviest first
    first = order[np.r_[True, part[order][1:] != part[order][:-1]]]
    return first[degree[first] > 0]


class TreeRotations(NamedTuple):
    rotations: np.ndarray    # (N, 3, 3) world-to-camera; NaN for images without a pair
    in_tree: np.ndarray      # (P,) bool: the pair is an edge of the tree


def spanning_tree_rotations(num_images: int, pairs: np.ndarray, R_relative: np.ndarray, weights: np.ndarray
                            ) -> TreeRotations:
    """R_j = R_ij R_i along the maximum-weight spanning tree of the pairs, R = I at each part's anchor.
    pairs (P, 2) without repeats, R_relative (P, 3, 3), weights (P,) > 0."""
    # The minimum spanning tree of 1 / weight is the tree of the heaviest pairs.
    tree = minimum_spanning_tree(_graph(num_images, pairs, 1.0 / weights))
    tree = tree + tree.T
    pair_of = {(i, j): k for k, (i, j) in enumerate(pairs.tolist())}
    rotations = np.full((num_images, 3, 3), np.nan)
    in_tree = np.zeros(len(pairs), bool)
    for anchor in anchors(num_images, pairs, weights):
        order, parent = breadth_first_order(tree, anchor, directed=False)
        rotations[anchor] = np.eye(3)
        for image in order[1:]:
            before = parent[image]
            if (before, image) in pair_of:
                k = pair_of[(before, image)]
                rotations[image] = R_relative[k] @ rotations[before]
            else:
                k = pair_of[(image, before)]
                rotations[image] = R_relative[k].T @ rotations[before]
            in_tree[k] = True
    return TreeRotations(rotations, in_tree)


def relative_residuals_deg(rotations: np.ndarray, pairs: np.ndarray, R_relative: np.ndarray) -> np.ndarray:
    """angle(R_ij, R_j R_i^T) of each pair, degrees; NaN where either rotation is unknown."""
    predicted = rotations[pairs[:, 1]] @ rotations[pairs[:, 0]].swapaxes(-1, -2)
    return rotation_angles_deg(R_relative, predicted)


def nearest_rotations(M: np.ndarray) -> np.ndarray:
    """The rotations nearest (Frobenius) to stacked 3x3 matrices: U diag(1, 1, det(U V^T)) V^T."""
    U, _, Vt = np.linalg.svd(M)
    flip = np.ones(M.shape[:-1])
    flip[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * flip[..., None, :]) @ Vt


def refined_rotations(initial: np.ndarray, pairs: np.ndarray, R_relative: np.ndarray, weights: np.ndarray,
                      scale_deg: float, iterations: int) -> np.ndarray:
    """argmin sum w_ij rho(angle(R_ij, R_j R_i^T)), rho Cauchy at scale_deg, by Jacobi sweeps from `initial`:
    R_i <- nearest rotation to sum w (R_ij^T R_j over pairs (i, j), R_ki R_k over pairs (k, i)). Images
    without a known initial rotation or without a pair here keep their initial one."""
    rotations = initial.copy()
    known = ~np.isnan(rotations[:, 0, 0])
    usable = known[pairs[:, 0]] & known[pairs[:, 1]]
    pairs, R_relative, weights = pairs[usable], R_relative[usable], weights[usable]
    i, j = pairs[:, 0], pairs[:, 1]
    moved = np.zeros(len(rotations), bool)
    moved[pairs.ravel()] = True
    for _ in range(iterations):
        w = weights / (1.0 + (relative_residuals_deg(rotations, pairs, R_relative) / scale_deg) ** 2)
        sums = np.zeros_like(rotations)
        np.add.at(sums, i, w[:, None, None] * (R_relative.swapaxes(-1, -2) @ rotations[j]))
        np.add.at(sums, j, w[:, None, None] * (R_relative @ rotations[i]))
        rotations[moved] = nearest_rotations(sums[moved])
    return rotations
