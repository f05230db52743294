"""Guided 2D-3D matching for an image whose registration failed on its tracks' correspondences.

An image's 2D-3D correspondences come from its tracks, i.e. from its pairwise matches: an image matched
with few registered images (a video frame beyond its neighbours' window, a view reached by a wide jump)
sees few of the model's points that way, although many of them lie in its view. Its weak pose hypothesis
(the absolute-pose RANSAC that failed the inlier minimums) predicts where each point of the model appears;
each keypoint of the image is then compared with the descriptors of the points predicted near it (every
observation's descriptor of a point, the closest one counting), which leaves few distractors for the ratio
test. What it finds is only evidence for the pose: the registration that uses it is estimated again and
held to the same checks (`verification`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree


class GuidedMatches(NamedTuple):
    """Keypoints of the image matched to points of the model."""

    keypoints: np.ndarray   # (G,) keypoint index in the image
    points: np.ndarray      # (G,) index into the candidate points given to `guided_matches`
    distances: np.ndarray   # (G,) descriptor distance of each match (the closest observation's)


def descriptor_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """||a_i - b_i|| = sqrt(2 - 2 a_i . b_i) row by row for unit-norm descriptors (RootSIFT)."""
    return np.sqrt(np.maximum(2.0 - 2.0 * np.einsum("ij,ij->i", a, b), 0.0))


def _rows_of(owner: np.ndarray, wanted: np.ndarray, num_owners: int) -> tuple[np.ndarray, np.ndarray]:
    """Every row r with owner[r] == wanted[k], for each k: (k of each, r of each), grouped by k."""
    order = np.argsort(owner, kind="stable")
    per_owner = np.bincount(owner, minlength=num_owners)
    start = np.cumsum(per_owner) - per_owner
    count = per_owner[wanted]
    of_wanted = np.repeat(np.arange(len(wanted)), count)
    within = np.arange(len(of_wanted)) - np.repeat(np.cumsum(count) - count, count)
    return of_wanted, order[np.repeat(start[wanted], count) + within]


def _first_per_group(group: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group, the element of smallest value and the group's second smallest value (inf without one)."""
    order = np.lexsort((value, group))
    first = np.ones(len(order), bool)
    first[1:] = group[order][1:] != group[order][:-1]
    position = np.flatnonzero(first)
    following = np.minimum(position + 1, len(order) - 1)
    has_second = (position + 1 < len(order)) & (group[order][following] == group[order][position])
    return order[position], np.where(has_second, value[order][following], np.inf)


def guided_matches(projected_uv: np.ndarray, descriptor_point: np.ndarray, point_descriptors: np.ndarray,
                   keypoint_uv: np.ndarray, keypoint_descriptors: np.ndarray, radius_px: float, ratio: float,
                   max_distance: float) -> GuidedMatches:
    """Keypoint k matches point p when p projects within radius_px of k (projected_uv (P, 2), keypoint_uv
    (N, 2)), d(k, p) = min over p's descriptors (point_descriptors (Q, 128) unit-norm, descriptor_point (Q,)
    their point) of ||d_k - d|| is at most max_distance and below ratio x d(k, p') of the next closest point
    p' near k (Lowe's test among the predicted candidates); each point keeps its closest keypoint."""
    empty = GuidedMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(projected_uv) == 0 or len(keypoint_uv) == 0:
        return empty
    near = cKDTree(keypoint_uv).query_ball_point(projected_uv, radius_px)
    pair_point = np.repeat(np.arange(len(projected_uv)), [len(keypoints) for keypoints in near])
    if len(pair_point) == 0:
        return empty
    pair_keypoint = np.concatenate(near).astype(np.int64)
    pair_of_row, row = _rows_of(np.asarray(descriptor_point, np.int64), pair_point, len(projected_uv))
    row_distance = descriptor_distances(point_descriptors[row],
                                        keypoint_descriptors[pair_keypoint[pair_of_row]])
    pair_distance = np.full(len(pair_point), np.inf)
    np.minimum.at(pair_distance, pair_of_row, row_distance)
    best, second = _first_per_group(pair_keypoint, pair_distance)
    chosen = best[(pair_distance[best] <= max_distance) & (pair_distance[best] < ratio * second)]
    closest, _ = _first_per_group(pair_point[chosen], pair_distance[chosen])
    chosen = chosen[closest]
    return GuidedMatches(pair_keypoint[chosen], pair_point[chosen], pair_distance[chosen])
