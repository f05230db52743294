"""Merging a second model into the first: the similarity that maps it into the first model's frame.

Two models of one set share tracks: a track triangulated in both gives one 3D-3D pair, and an image of one
model that sees a point of the other gives a cross-model 2D-3D correspondence. The 3D-3D pairs are few and
noisy on weakly linked models (on a sparse ring, 36 pairs of which 10 fit one similarity), so they only
propose hypotheses (Umeyama on three pairs); each hypothesis is judged by the pixels: how many cross-model
correspondences it reprojects within the absolute-pose threshold, in the images of both models. A wrong
similarity that fits three pairs by chance does not put many points of one model onto their keypoints in
the other's images, and the moved points must lie on the surface the first model reconstructed (on a
sparse ring, a similarity 25 deg off the truth reprojected 84 cross-model correspondences, the true one 94,
but 22 % of its moved points lay near the other model's against 59 %). Pure functions; the mapper
(`incremental`) decides whether to merge.
"""

from __future__ import annotations

from itertools import combinations
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from estimation.geometry.alignment import Similarity, align_similarity
from estimation.geometry.linalg import rotation_from_rotvec

SIMILARITY_SAMPLE = 3
"""Point pairs that determine a similarity."""
SIMILARITY_DOF = 7
"""Scale, rotation and translation: a re-fit needs as many inlier residuals."""
HYPOTHESES_PER_BATCH = 512
"""Similarities scored at once (memory: batch x correspondences x 3 floats)."""


class CrossCorrespondences(NamedTuple):
    """Keypoints of one model's images and the other model's points their tracks reached: the camera
    (world-to-camera, in the keypoints' model frame) of each keypoint and the point (in the other frame)."""

    R: np.ndarray       # (N, 3, 3) camera rotation of each keypoint's image
    t: np.ndarray       # (N, 3)
    uv: np.ndarray      # (N, 2) working pixels of the pinhole K
    points: np.ndarray  # (N, 3) the other model's point of the keypoint's track


class ModelMerge(NamedTuple):
    """The similarity X_first = s R X_second + t best supported by the cross-model correspondences."""

    similarity: Similarity
    inliers: int            # cross-model correspondences reprojected within the threshold
    correspondences: int    # all cross-model correspondences (both directions)
    shared_points: int      # 3D-3D pairs the hypotheses were drawn from
    hypotheses: int


def inverse_similarity(similarity: Similarity) -> Similarity:
    """X = s^-1 R^T (X' - t), the inverse of X' = s R X + t."""
    R_inverse = similarity.R.T
    return Similarity(1.0 / similarity.scale, R_inverse, -R_inverse @ similarity.t / similarity.scale)


def similarity_samples(num_pairs: int, max_samples: int, rng: np.random.Generator) -> np.ndarray:
    """(S, 3) index triples of the 3D-3D pairs: every triple when there are at most max_samples, else
    max_samples random ones (without repeats within a triple)."""
    total = num_pairs * (num_pairs - 1) * (num_pairs - 2) // 6
    if total <= max_samples:
        return np.array(list(combinations(range(num_pairs), SIMILARITY_SAMPLE)), np.int64).reshape(-1, 3)
    return np.argpartition(rng.random((max_samples, num_pairs)), SIMILARITY_SAMPLE - 1,
                           axis=1)[:, :SIMILARITY_SAMPLE]


def cross_errors(scale: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                 cross: CrossCorrespondences) -> np.ndarray:
    """(H, N) ||pi(K (R_n (s_h R_h X_n + t_h) + t_n)) - uv_n|| in pixels (inf behind camera n) for
    similarities h (scale (H,), R (H, 3, 3), t (H, 3)) taking the points into the keypoints' frame."""
    moved = scale[:, None, None] * np.einsum("hij,nj->hni", R, cross.points) + t[:, None, :]
    in_camera = np.einsum("nij,hnj->hni", cross.R, moved) + cross.t
    depth = in_camera[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        projected = in_camera[..., :2] / depth[..., None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        errors = np.linalg.norm(projected - cross.uv, axis=-1)
    return np.where(depth > 0, errors, np.inf)


def both_ways_errors(similarities: list[Similarity], K: np.ndarray, into_first: CrossCorrespondences,
                     into_second: CrossCorrespondences) -> np.ndarray:
    """(H, N1 + N2) `cross_errors` of each similarity S (second -> first) on into_first and of S^-1 on
    into_second."""
    inverses = [inverse_similarity(h) for h in similarities]

    def errors(stack: list[Similarity], cross: CrossCorrespondences) -> np.ndarray:
        return cross_errors(np.array([h.scale for h in stack]), np.array([h.R for h in stack]),
                            np.array([h.t for h in stack]), K, cross)

    return np.concatenate([errors(similarities, into_first), errors(inverses, into_second)], axis=1)


def refined_similarity(similarity: Similarity, K: np.ndarray, into_first: CrossCorrespondences,
                       into_second: CrossCorrespondences, inliers: np.ndarray) -> Similarity:
    """argmin over (s, R, t) of sum over the inlier correspondences of their squared `both_ways_errors`
    (Levenberg-Marquardt from `similarity`, parameters log s, a rotation vector on R, t)."""
    def moved(p: np.ndarray) -> Similarity:
        return Similarity(similarity.scale * np.exp(p[0]), rotation_from_rotvec(p[1:4]) @ similarity.R,
                          similarity.t + p[4:])

    def residuals(p: np.ndarray) -> np.ndarray:
        errors = both_ways_errors([moved(p)], K, into_first, into_second)[0, inliers]
        return np.where(np.isfinite(errors), errors, 1e3)

    return moved(least_squares(residuals, np.zeros(SIMILARITY_DOF), method="lm").x)


def merge_similarity(points_second: np.ndarray, points_first: np.ndarray, K: np.ndarray,
                     into_first: CrossCorrespondences, into_second: CrossCorrespondences,
                     threshold_px: float, max_samples: int, seed: int, refits: int) -> ModelMerge | None:
    """argmax over Umeyama similarities of 3-pair samples of (points_second, points_first) (P, 3) of the
    cross-model inliers: `into_first` holds the first model's keypoints with the second's points (moved by
    S), `into_second` the second's keypoints with the first's points (moved by S^-1); the best is re-fitted
    on its inliers (`refined_similarity`) up to `refits` times while they grow. None without 3 pairs."""
    if len(points_first) < SIMILARITY_SAMPLE:
        return None
    samples = similarity_samples(len(points_first), max_samples, np.random.default_rng(seed))
    hypotheses = [align_similarity(points_second[sample], points_first[sample]) for sample in samples]
    hypotheses = [h for h in hypotheses if np.isfinite(h.scale) and h.scale > 0 and np.all(np.isfinite(h.t))]
    if not hypotheses:
        return None
    counts = np.concatenate([
        (both_ways_errors(hypotheses[start:start + HYPOTHESES_PER_BATCH], K, into_first, into_second)
         < threshold_px).sum(axis=1) for start in range(0, len(hypotheses), HYPOTHESES_PER_BATCH)])
    best = hypotheses[int(counts.argmax())]
    inliers = both_ways_errors([best], K, into_first, into_second)[0] < threshold_px
    # Local optimization: re-fit on the consensus while it grows (a 3-pair fit of noisy points is rough).
    for _ in range(refits if inliers.sum() >= SIMILARITY_DOF else 0):
        candidate = refined_similarity(best, K, into_first, into_second, inliers)
        candidate_inliers = both_ways_errors([candidate], K, into_first, into_second)[0] < threshold_px
        if candidate_inliers.sum() <= inliers.sum():
            break
        best, inliers = candidate, candidate_inliers
    return ModelMerge(best, int(inliers.sum()), len(into_first.uv) + len(into_second.uv),
                      len(points_first), len(hypotheses))


def surface_overlap(points: np.ndarray, reference: np.ndarray, spacings: float) -> float:
    """#{p in points : min_q ||p - q|| <= spacings x median nearest-neighbour distance of the reference
    points q} / #points: how much of a moved model lies on the surface the other model reconstructed (two
    models of one object overlap where their views do; a wrongly rotated one floats beside it)."""
    if len(points) == 0 or len(reference) < 2:
        return 0.0
    tree = cKDTree(reference)
    spacing = float(np.median(tree.query(reference, k=2)[0][:, 1]))
    return float((tree.query(points)[0] <= spacings * spacing).mean())


def merge_problem(merge: ModelMerge | None, overlap: float, min_inliers: float, min_overlap: float
                  ) -> str | None:
    """Why the merge is too weakly supported (cross-model inliers >= min_inliers and the moved points'
    `surface_overlap` >= min_overlap), or None."""
    if merge is None:
        return "the models share fewer than 3 triangulated tracks"
    if merge.inliers < min_inliers:
        return (f"the best similarity of {merge.hypotheses} (from {merge.shared_points} shared points) "
                f"reprojects {merge.inliers} of {merge.correspondences} cross-model 2D-3D correspondences "
                f"(need {int(np.ceil(min_inliers))})")
    if overlap < min_overlap:
        return (f"{overlap:.0%} of its points moved by the best similarity lie on the other model's surface "
                f"(need {min_overlap:.0%})")
    return None
