"""Guided 2D-3D matching for an image whose registration failed on its tracks' correspondences.

An image's 2D-3D correspondences come from its tracks, i.e. from its pairwise matches: an image matched
with few registered images (a video frame beyond its neighbours' window, a view reached by a wide jump)
sees few of the model's points that way, although many of them lie in its view. Its weak pose hypothesis
(the absolute-pose RANSAC that failed the inlier minimums) predicts which points are in view and where;
each keypoint of the image is matched to its nearest point in view by descriptor (a point's distance: that
of its closest observation's RootSIFT), kept when it passes the ratio test over every point in
view and the point is predicted near the keypoint. What it finds is only evidence for the pose: the
registration that uses it is estimated again and held to the same checks (`verification`).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class GuidedMatches(NamedTuple):
    """Keypoints of the image matched to points of the model."""

    keypoints: np.ndarray   # (G,) keypoint index in the image
    points: np.ndarray      # (G,) index into the candidate points given to `guided_matches`
    distances: np.ndarray   # (G,) descriptor distance of each match (the closest observation's)


SIMILARITY_ENTRIES = 1 << 24
"""Most entries of one keypoints x descriptors similarity block (64 MB of float32): the keypoints are
compared with the points' descriptors in blocks of this many over the descriptors' count."""


def guided_matches(projected_uv: np.ndarray, descriptor_point: np.ndarray, point_descriptors: np.ndarray,
                   keypoint_uv: np.ndarray, keypoint_descriptors: np.ndarray, radius_px: float, ratio: float,
                   max_distance: float) -> GuidedMatches:
    """Keypoint k (keypoint_uv (N, 2), unit-norm descriptors (N, D)) matches point p (projected_uv (P, 2):
    the points in the predicted view, each with the unit-norm descriptors (Q, D) of its observations,
    descriptor_point (Q,) naming their point) when p is its nearest point in descriptor space (a point's
    distance: its closest observation's), d1 <= max_distance and d1 < ratio x d2 (d2: the second nearest
    point in view: Lowe's test over the whole view, so that a repeated texture is refused rather than
    matched to whichever copy the prediction lies near), and p projects within radius_px of k; each point
    keeps its closest keypoint."""
    num_points = len(projected_uv)
    if num_points < 2 or len(keypoint_uv) == 0:
        return GuidedMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    order = np.argsort(descriptor_point, kind="stable")
    rows = np.asarray(point_descriptors, np.float32)[order]
    starts = np.searchsorted(descriptor_point[order], np.arange(num_points))   # every point has a row
    nearest, similarities = [], []
    block_size = max(1, SIMILARITY_ENTRIES // len(rows))
    for start in range(0, len(keypoint_uv), block_size):
        block = np.asarray(keypoint_descriptors[start:start + block_size], np.float32)
        per_point = np.maximum.reduceat(block @ rows.T, starts, axis=1)       # (B, P) closest observation
        two = np.argpartition(-per_point, 1, axis=1)[:, :2]
        best = np.take_along_axis(per_point, two, axis=1)
        swap = best[:, 1] > best[:, 0]
        two[swap], best[swap] = two[swap][:, ::-1], best[swap][:, ::-1]
        nearest.append(two[:, 0])
        similarities.append(best)
    point, best = np.concatenate(nearest), np.concatenate(similarities)
    first, second = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0)).T
    near = np.linalg.norm(projected_uv[point] - keypoint_uv, axis=1) <= radius_px
    chosen = np.flatnonzero((first <= max_distance) & (first < ratio * second) & near)
    closest = np.lexsort((first[chosen], point[chosen]))
    keep = np.ones(len(closest), bool)
    keep[1:] = point[chosen][closest][1:] != point[chosen][closest][:-1]
    chosen = chosen[closest[keep]]
    return GuidedMatches(chosen, point[chosen], first[chosen])
