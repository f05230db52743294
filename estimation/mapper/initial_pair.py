"""The pair a model starts from: candidates from the image graph, each tried until one works.

Candidates are the co-visible pairs ranked by shared (verified) tracks. Each is evaluated in turn:
geometric verification (`two_view.geometry`: E by the 5-point solver, F and H in RANSAC; planar and
panoramic pairs are refused), the chirality-checked relative pose of E estimated again on the inliers at
a tight threshold (`tight_essential`), triangulation of the inliers, and their parallax. A candidate
passes with enough well-conditioned points and a median triangulation angle at
min_initial_pair_median_angle_deg; the first reaching preferred_initial_pair_angle_deg is taken at once
(wide baselines start better conditioned models), else the one with most well-conditioned points among
the first initial_pair_candidates passing ones. A failed candidate only records its reason: the next is
tried while the graph has pairs left (COLMAP tries pairs the same way).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
from scipy import sparse

from estimation.config import ReconstructionConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.projection import reprojection_errors
from estimation.geometry.triangulation import (
    observations_for_pair,
    triangulate_nonlinear,
    triangulation_angle_deg,
)
from estimation.two_view.essential import choose_relative_pose, essential_from_fundamental, ransac_essential
from estimation.two_view.fundamental import MIN_CORRESPONDENCES as MIN_F_CORRESPONDENCES
from estimation.two_view.geometry import estimate_two_view_geometry
from estimation.types import CameraPose, Tracks

EXCLUDED_PAIR_TYPES = frozenset({"planar", "panoramic", "planar_or_panoramic"})
"""Two-view geometry labels (from geometric verification) that cannot start a model: no parallax to
triangulate from, or a homography explains the pair as well as F does."""


class PairGeometry(NamedTuple):
    """Correspondences of one image pair through shared tracks, and their verified essential matrix."""

    i: int
    j: int
    track_ids: np.ndarray
    uv_i: np.ndarray
    uv_j: np.ndarray
    E: np.ndarray  # x_j^T E x_i = 0 on normalized coordinates
    inlier_mask: np.ndarray  # (K,) inliers of the verified model


class InitialPairCandidate(NamedTuple):
    """A pair triangulated in its own frame (camera i at the origin, baseline 1)."""

    geometry: PairGeometry
    pose_j: CameraPose
    track_ids: np.ndarray  # (L,) inlier tracks in front of both cameras
    points_linear: np.ndarray  # (L, 3)
    points: np.ndarray  # (L, 3) non-linear
    well_conditioned: np.ndarray  # (L,) bool: error and angle within the filter limits
    median_angle_deg: float  # of the well-conditioned points
    narrow: int  # points seen at less than the filter's minimum triangulation angle
    far_off: int  # points reprojecting beyond the filter's maximum error


class InitialPairChoice(NamedTuple):
    """The chosen candidate (None when every pair failed) and why each evaluated pair failed."""

    candidate: InitialPairCandidate | None
    failures: dict[tuple[int, int], str]


def pair_name(tracks: Tracks, i: int, j: int) -> str:
    return f"{tracks.image_names[i]}|{tracks.image_names[j]}"


def co_visible_pairs(tracks: Tracks) -> list[tuple[int, int, int]]:
    """(i, j, shared tracks) for every image pair i < j sharing at least one track."""
    visibility = sparse.csr_matrix(
        (np.ones(len(tracks.track_index)), (tracks.track_index, tracks.image_index)),
        shape=(tracks.num_tracks, len(tracks.image_names)),
    )
    shared = sparse.triu(visibility.T @ visibility, k=1).tocoo()
    return [(int(i), int(j), int(n)) for i, j, n in zip(shared.row, shared.col, shared.data, strict=True)]


def evaluate_initial_pair(
    K: np.ndarray, geometry: PairGeometry, config: ReconstructionConfig
) -> InitialPairCandidate:
    """Chirality of E's four poses, DLT + non-linear triangulation of the inliers, and their parallax."""
    inliers = geometry.inlier_mask
    uv_i, uv_j = geometry.uv_i[inliers], geometry.uv_j[inliers]
    relative = choose_relative_pose(geometry.E, K, uv_i, uv_j)
    front = relative.in_front
    pose_j = relative.pose
    obs = observations_for_pair(np.eye(3), np.zeros(3), pose_j.R, pose_j.t, uv_i[front], uv_j[front])
    points = triangulate_nonlinear(K, obs, relative.points[front]).points
    errors = reprojection_errors(K, obs, points).reshape(2, -1).max(axis=0)
    centers = np.concatenate([np.zeros((front.sum(), 3)), np.broadcast_to(pose_j.center, (front.sum(), 3))])
    angles = triangulation_angle_deg(centers, obs.point_index, points)
    accurate = errors <= config.filter.max_reprojection_px
    wide = angles >= config.filter.min_triangulation_angle_deg
    well_conditioned = accurate & wide
    return InitialPairCandidate(
        geometry=geometry,
        pose_j=pose_j,
        track_ids=geometry.track_ids[inliers][front],
        points_linear=relative.points[front],
        points=points,
        well_conditioned=well_conditioned,
        median_angle_deg=float(np.median(angles[well_conditioned])) if well_conditioned.any() else 0.0,
        narrow=int((~wide).sum()),
        far_off=int((~accurate).sum()),
    )


def tight_essential(K: np.ndarray, E: np.ndarray, uv_i: np.ndarray, uv_j: np.ndarray,
                    config: ReconstructionConfig) -> np.ndarray:
    """argmax_E #{Sampson distance < initial_pair_max_error_px} over the verified inliers uv_i, uv_j (5-point
    RANSAC, polished), or the verified `E` when fewer than min_initial_pair_inliers fit that tightly.

    Verification's 4 px admits, on small images, essential matrices several degrees apart with as many
    inliers: on lego's 200 px views, its E of the pair that started a flipped model (all 90 images 160 deg
    off) was 21 deg from the true relative rotation."""
    try:
        estimate = ransac_essential(uv_i, uv_j, K, K, config.mapper.initial_pair_max_error_px, config.ransac)
    except DegenerateConfigurationError:
        return E
    return estimate.E if estimate.inlier_mask.sum() >= config.mapper.min_initial_pair_inliers else E


def _try_pair(
    K: np.ndarray, tracks: Tracks, i: int, j: int, config: ReconstructionConfig
) -> InitialPairCandidate | str:
    """The evaluated candidate when it passes, else the reason it cannot start a model."""
    mapper = config.mapper
    track_ids, uv_i, uv_j = tracks.pair_correspondences(i, j)
    if len(track_ids) < max(MIN_F_CORRESPONDENCES, mapper.min_initial_pair_inliers):
        need = mapper.min_initial_pair_inliers
        return f"{len(track_ids)} shared tracks, need {need} (min_initial_pair_inliers)"
    verified = estimate_two_view_geometry(uv_i, uv_j, K, K, config.two_view, config.ransac)
    if not verified.can_initialize:
        return (f"geometric verification labels it {verified.type} ({verified.num_inliers_f} F, "
                f"{verified.num_inliers_e} E, {verified.num_inliers_h} H inliers)")
    E = verified.E if verified.E is not None else essential_from_fundamental(verified.F, K)
    if config.two_view.relative_pose == "five-point":    # the seed's path keeps its E = K^T F K
        E = tight_essential(K, E, uv_i[verified.inlier_mask], uv_j[verified.inlier_mask], config)
    candidate = evaluate_initial_pair(
        K, PairGeometry(i, j, track_ids, uv_i, uv_j, E, verified.inlier_mask), config
    )
    well = int(candidate.well_conditioned.sum())
    if well < mapper.min_initial_pair_inliers:
        return (f"{well} of {verified.num_inliers} RANSAC inliers triangulate well conditioned "
                f"({candidate.narrow} seen at under {config.filter.min_triangulation_angle_deg} deg: "
                f"{'too little parallax, ' if candidate.narrow > well else ''}{candidate.far_off} reproject "
                f"beyond {config.filter.max_reprojection_px} px), need {mapper.min_initial_pair_inliers} "
                "(min_initial_pair_inliers)")
    if candidate.median_angle_deg < mapper.min_initial_pair_median_angle_deg:
        return (f"median triangulation angle {candidate.median_angle_deg:.2f} deg is below "
                f"{mapper.min_initial_pair_median_angle_deg} deg (pure rotation or too little parallax)")
    return candidate


def choose_initial_pair(
    K: np.ndarray,
    tracks: Tracks,
    pairs: Iterable[tuple[int, int, int]],
    config: ReconstructionConfig,
    pair_types: dict[tuple[int, int], str] | None = None,
) -> InitialPairChoice:
    """The first passing candidate (most shared tracks first) reaching preferred_initial_pair_angle_deg,
    else the best of the first initial_pair_candidates passing ones (or of all that pass); pairs labelled
    planar/panoramic by verification are skipped. Never raises for a failed candidate."""
    mapper = config.mapper
    failures: dict[tuple[int, int], str] = {}
    ranked = sorted(pairs, key=lambda pair: (-pair[2], pair[0], pair[1]))
    batch: list[InitialPairCandidate] = []
    for i, j, _ in ranked:
        label = (pair_types or {}).get((i, j))
        if label in EXCLUDED_PAIR_TYPES:
            failures[(i, j)] = f"geometric verification labels it {label}"
            continue
        outcome = _try_pair(K, tracks, i, j, config)
        if isinstance(outcome, str):
            failures[(i, j)] = outcome
            continue
        if outcome.median_angle_deg >= mapper.preferred_initial_pair_angle_deg:
            return InitialPairChoice(outcome, failures)
        batch.append(outcome)
        if len(batch) >= mapper.initial_pair_candidates:
            break
    if not batch:
        return InitialPairChoice(None, failures)
    best = max(
        batch,
        key=lambda c: (
            c.median_angle_deg >= mapper.preferred_initial_pair_angle_deg,
            int(c.well_conditioned.sum()),
            c.median_angle_deg,
        ),
    )
    return InitialPairChoice(best, failures)
