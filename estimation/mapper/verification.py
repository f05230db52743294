"""Checks of an image's registration against evidence its pose was not fitted to.

A pose from absolute-pose RANSAC explains its own inliers by construction; on a symmetric object a pose on
the far side of the ring can explain as many (the features of both sides look alike), with a low
reprojection error. So each registration is also held against:
- its support: inliers and inlier ratio (COLMAP keeps >= 30 and >= 25 %), the inliers' spread over the
  image (a pose resting on one corner is poorly constrained), and how closely they pin its rotation at 1 px
  of noise: a dozen inliers on a narrow, shallow patch fit a rotation several degrees off (with a shifted
  centre) about as well as the true one;
- the relative rotations that two-view geometry verified for its pairs with registered images, which were
  estimated from the pair's own matches, not from the model's points: a placement on the far side of the
  ring disagrees by ~180 deg with every true neighbour. Without calibration a pair verified only F, and
  the rotation of E = K^T F K depends on K: it is taken under the model's current (self-calibrated)
  intrinsics, not the initial focal prior, and only when that E is an essential matrix (two equal
  singular values): a wide, near-planar pair's F can be consistent with its matches and still give a
  rotation 90 deg off under the right K.
A finished model is also held against what its cameras do not observe: two cameras placed at the same
viewpoint see the same points, so a pair there that shares few of them was put there by look-alike
features (a model folded onto itself by a symmetric object; `shared_views`).
Each check is a pure function with a typed result; the mapper (`incremental`) decides what to do.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from estimation.geometry.alignment import relative_pose, rotation_angles_deg
from estimation.geometry.linalg import skew
from estimation.geometry.projection import Camera, project
from estimation.two_view.essential import (
    essential_rotations,
    fundamental_from_essential,
    project_to_essential,
)
from estimation.two_view.fundamental import sampson_distance
from estimation.two_view.geometry import TwoViewGeometry
from estimation.types import CameraPose

NEAR_MIRROR = "a near-mirror placement"
"""The words that end a refusal for disagreeing with the verified pairs (the warnings look for them)."""
MIRROR_AMBIGUITY = "near-mirror ambiguity"
"""How the warnings of images placed or tried on the other side of a symmetric object begin."""
FOLDED = "possibly folded onto itself by a symmetric object"
"""How the warning of a model whose cameras at one viewpoint share few points begins (`shared_views`)."""
LOOSE_ROTATION = "a loosely pinned rotation"
"""The words that end a refusal for inliers that pin the rotation too loosely (`rotation_std_problem`)."""
SPREAD_GRID = 8
"""Cells per side of the grid that measures the inliers' spread over the image (64 cells)."""


class InlierSupport(NamedTuple):
    """How much of an image's 2D-3D correspondences a registration explains, and where they lie."""

    inliers: int
    correspondences: int
    spread: float           # share of the image's grid cells holding an inlier (`inlier_spread`)

    @property
    def ratio(self) -> float:
        return self.inliers / max(self.correspondences, 1)


def inlier_spread(inlier_uv: np.ndarray, width: float, height: float, grid: int = SPREAD_GRID) -> float:
    """#cells holding an inlier / grid^2, on a grid x grid split of the width x height image: a pose resting
    on a few cells (one corner, one small part of the object) is poorly constrained. (Relative to where
    the correspondences lie it would not work: the wrong ones lie anywhere.)"""
    uv = np.asarray(inlier_uv, float).reshape(-1, 2)
    index = np.clip((uv / [width, height] * grid).astype(np.int64), 0, grid - 1)
    return len(np.unique(index[:, 0] * grid + index[:, 1])) / grid**2


def support_problem(support: InlierSupport, min_inliers: float, min_ratio: float, min_spread: float
                    ) -> str | None:
    """Why the support is too weak (inliers >= min_inliers, ratio >= min_ratio, spread >= min_spread),
    or None."""
    if support.inliers < min_inliers or support.ratio < min_ratio:
        return (f"absolute pose RANSAC found {support.inliers} inliers among {support.correspondences} 2D-3D "
                f"correspondences (need {int(np.ceil(min_inliers))} and {min_ratio:.0%})")
    if support.spread < min_spread:
        return (f"its {support.inliers} inliers lie in {support.spread:.0%} of the image's "
                f"{SPREAD_GRID}x{SPREAD_GRID} cells (need {min_spread:.0%})")
    return None


def pose_rotation_std_deg(K: np.ndarray, pose: CameraPose, points: np.ndarray, pixel_sigma: float) -> float:
    """sqrt(lambda_max(S_w)) in degrees, S = sigma^2 (J^T J)^-1 over [w, dt] (R <- exp([w]x) R, t <- t + dt),
    J_k = d pi(K x) / dx [-[R X_k]x | I] at x = R X_k + t: how closely the points' reprojections pin the
    pose's rotation at pixel_sigma px of noise (inf when they do not determine it)."""
    rotated = np.asarray(points, float) @ pose.R.T
    camera = rotated + pose.t
    depth = camera[:, 2]
    pixel = camera @ K.T / depth[:, None]
    # d pi / dx = (K[:2] - pixel[:2] e_3^T) / z, per point (N, 2, 3)
    d_pi = (K[None, :2, :] - pixel[:, :2, None] * np.array([0.0, 0.0, 1.0])) / depth[:, None, None]
    jacobian = np.concatenate([d_pi @ -skew(rotated), d_pi], axis=2).reshape(-1, 6)
    information = jacobian.T @ jacobian
    if np.linalg.cond(information) > 1e12:
        return float("inf")
    rotation_covariance = pixel_sigma**2 * np.linalg.inv(information)[:3, :3]
    return float(np.degrees(np.sqrt(np.linalg.eigvalsh(rotation_covariance).max())))


def rotation_std_problem(std_deg: float, max_std_deg: float, inliers: int) -> str | None:
    """Why a pose's rotation is too loosely determined (`pose_rotation_std_deg` at 1 px above max_std_deg),
    or None."""
    if std_deg <= max_std_deg:
        return None
    return (f"its {inliers} inliers determine its rotation only to {std_deg:.1f} deg (one std-dev at 1 px "
            f"of noise; need {max_std_deg:g} deg): {LOOSE_ROTATION}")


def essential_rotation_deviations_deg(rotations: np.ndarray, R_relative: np.ndarray) -> np.ndarray:
    """min over the two rotations R of E (`essential_rotations`) of angle(R, R_relative): how far a relative
    rotation (x_2 = R_relative x_1 + t) is from the pair's verified epipolar geometry, without chirality
    (a far-side placement is far from both); stacked pairs: rotations (..., 2, 3, 3), R_relative (..., 3, 3)
    -> (...)."""
    return rotation_angles_deg(rotations, R_relative[..., None, :, :]).min(axis=-1)


class VerifiedPair(NamedTuple):
    """Two-view evidence about image `image` relative to the registered image `other`."""

    other: int
    rotations: np.ndarray | None  # (2, 3, 3) `essential_rotations` of E, x_image^T E x_other = 0
                                  # (normalized); None while it rests on F (`under_intrinsics` gives them)
    inliers: int                  # the pair's verified inliers: the weight of its vote
    F: np.ndarray | None = None   # pixels, x_image^T F x_other = 0: the pair's geometry without calibration
    E: np.ndarray | None = None   # normalized, x_image^T E x_other = 0: its verified E (without
                                  # calibration, the one `under_intrinsics` takes from F)


def voting_pairs(geometries: dict[tuple[int, int], TwoViewGeometry], num_images: int,
                 min_inliers: int) -> list[list[VerifiedPair]]:
    """Image m -> its verified pairs with >= min_inliers inliers, E (or F) oriented so that
    x_m^T E x_other = 0 (E of pair (i, j) relates x_j^T E x_i = 0, so image i gets E^T); a pair with F only
    (no calibration) gets its rotations from `under_intrinsics`."""
    votes: list[list[VerifiedPair]] = [[] for _ in range(num_images)]
    with_E = [pair for pair, geometry in geometries.items()
              if geometry.num_inliers >= min_inliers and geometry.E is not None]
    # All at once: one batched SVD instead of one per pair and direction (0.03 s of lego's mapping). E^T ~
    # [R^T t]x R^T, so the rotations of E^T are the transposes of E's.
    E = np.stack([geometries[pair].E for pair in with_E]) if with_E else np.zeros((0, 3, 3))
    of_E = essential_rotations(E)
    rotations = dict(zip(with_E, zip(of_E, of_E.swapaxes(-1, -2), strict=True), strict=True))
    for (i, j), geometry in geometries.items():
        if geometry.num_inliers < min_inliers or (geometry.E is None and geometry.F is None):
            continue
        if geometry.E is not None:
            of_j, of_i = rotations[(i, j)]
            votes[j].append(VerifiedPair(i, of_j, geometry.num_inliers, E=geometry.E))
            votes[i].append(VerifiedPair(j, of_i, geometry.num_inliers, E=geometry.E.T))
        else:
            votes[j].append(VerifiedPair(i, None, geometry.num_inliers, geometry.F))
            votes[i].append(VerifiedPair(j, None, geometry.num_inliers, geometry.F.T))
    return votes


def under_intrinsics(pair: VerifiedPair, K_image: np.ndarray, K_other: np.ndarray,
                     min_singular_ratio: float) -> VerifiedPair | None:
    """A pair resting on F with E = K_image^T F K_other and its rotations (pixel K of each image: the model's
    current ones), or None (no vote) when that E is no essential matrix: its singular values s_2 / s_1 <
    min_singular_ratio (F disagrees with those intrinsics); a pair with a verified E as it is."""
    if pair.F is None:
        return pair
    E = K_image.T @ pair.F @ K_other
    singular = np.linalg.svd(E, compute_uv=False)
    if singular[1] < min_singular_ratio * singular[0]:
        return None
    E = project_to_essential(E)
    return pair._replace(rotations=essential_rotations(E), E=E)


def pair_fundamental(pair: VerifiedPair, K: np.ndarray) -> np.ndarray:
    """The pair's own epipolar geometry in pixels of K, x_image^T F x_other = 0: F = K^-T E K^-1 of its
    verified E (without calibration, the E that `under_intrinsics` took from its F)."""
    return fundamental_from_essential(pair.E, K, K)


def pose_fundamental(K: np.ndarray, image: CameraPose, other: CameraPose) -> np.ndarray:
    """F = K^-T [t]x R K^-1 of two world-to-camera poses, (R, t) = `relative_pose(other, image)`
    (x_image^T F x_other = 0, pixels of K)."""
    relative = relative_pose(other, image)
    return fundamental_from_essential(skew(relative.t) @ relative.R, K, K)


def epipolar_share(F: np.ndarray, uv_image: np.ndarray, uv_other: np.ndarray, threshold_px: float) -> float:
    """#{i : sampson_i(x_image^T F x_other) < threshold_px} / N: the share of correspondences F explains."""
    return float((sampson_distance(F, uv_other, uv_image) < threshold_px).mean()) if len(uv_image) else 0.0


class RotationAgreement(NamedTuple):
    """How a pose's relative rotations agree with the verified pairs (the votes weighted by inliers)."""

    agreeing_inliers: int
    voting_inliers: int
    deviations_deg: dict[int, float]   # other image -> deviation of the pose from that pair's E

    @property
    def share(self) -> float:
        """Agreeing over voting inliers (1 without votes: nothing contradicts the pose)."""
        return self.agreeing_inliers / self.voting_inliers if self.voting_inliers else 1.0


def rotation_agreement(R_image: np.ndarray, pairs: list[VerifiedPair], R_of: dict[int, np.ndarray],
                       max_deviation_deg: float) -> RotationAgreement:
    """Each pair votes with its inliers for or against R_image: for when R_image R_other^T is within
    max_deviation_deg of its E's rotation (`essential_rotation_deviations_deg`); R_of: other -> its R."""
    if not pairs:
        return RotationAgreement(0, 0, {})
    R_others = np.stack([R_of[pair.other] for pair in pairs])
    deviations = essential_rotation_deviations_deg(np.stack([pair.rotations for pair in pairs]),
                                                   R_image @ np.swapaxes(R_others, -1, -2))
    inliers = np.array([pair.inliers for pair in pairs])
    agreeing = int(inliers[deviations <= max_deviation_deg].sum())
    return RotationAgreement(agreeing, int(inliers.sum()),
                             dict(zip([pair.other for pair in pairs], deviations.tolist(), strict=True)))


def agreement_problem(agreement: RotationAgreement, min_share: float, image_names: list[str]) -> str | None:
    """Why the rotation agreement is too weak (share of agreeing inliers below min_share), or None."""
    if agreement.share >= min_share:
        return None
    worst = max(agreement.deviations_deg, key=agreement.deviations_deg.get)
    return (f"its rotation disagrees with the verified two-view geometry of its pairs ({agreement.share:.0%} "
            f"of their inliers agree, need {min_share:.0%}; {agreement.deviations_deg[worst]:.0f} deg off "
            f"the pair with {image_names[worst]}): {NEAR_MIRROR}")


class SharedView(NamedTuple):
    """Two registered cameras placed near each other's viewpoint, and how much of what one observes the
    other observes too."""

    image_a: int
    image_b: int
    angle_deg: float    # the larger of their relative rotation and their baseline seen from their points
    shared: float       # the smaller of the two ways (`shared_views`)


def shared_views(poses: dict[int, CameraPose], cameras: Sequence[Camera], image_size: tuple[float, float],
                 points: np.ndarray, obs_image: np.ndarray, obs_point: np.ndarray, max_angle_deg: float
                 ) -> list[SharedView]:
    """shared = min over both ways of |P_a & P_b| / |{X in P_a : in front of b, inside its image}| (P_m: the
    points image m observes) for every pair within max_angle_deg of each other's viewpoint: their relative
    rotation, and atan(baseline / the nearer median depth of their points). Cameras at one viewpoint
    observe the same points (lego_200's and lego_ring_400's pairs within 5 deg share 56 % or more)."""
    images = sorted(poses)
    if len(images) < 2:
        return []
    R = np.stack([poses[m].R for m in images])
    # Candidates first: optical axes within the angle (a rotation turns the axis by at most its angle), so
    # that a model of thousands of images never compares every pair.
    chord = 2.0 * np.sin(np.radians(min(max_angle_deg, 180.0)) / 2.0)
    candidates = cKDTree(R[:, 2]).query_pairs(chord, output_type="ndarray")
    if len(candidates) == 0:
        return []
    first, second = candidates[np.lexsort(candidates.T[::-1])].T
    observed = {m: np.unique(obs_point[obs_image == m]) for m in images}
    centres = np.stack([poses[m].center for m in images])
    depth = np.array([np.median(points[observed[m]] @ poses[m].R[2] + poses[m].t[2]) if len(observed[m])
                      else np.inf for m in images])
    rotation = rotation_angles_deg(R[first], R[second])
    baseline = np.linalg.norm(centres[first] - centres[second], axis=1)
    parallax = np.degrees(np.arctan(baseline / np.minimum(depth[first], depth[second])))
    angle = np.maximum(rotation, parallax)
    width, height = image_size
    views = []
    close = angle <= max_angle_deg
    for a, b, pair_angle in zip(first[close], second[close], angle[close], strict=True):
        both = len(np.intersect1d(observed[images[a]], observed[images[b]], assume_unique=True))
        shares = []
        for one, other in ((images[a], images[b]), (images[b], images[a])):
            projection = project(cameras[other], poses[other].R, poses[other].t, points[observed[one]])
            uv = projection.uv
            inside = ((projection.depth > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < width)
                      & (uv[:, 1] < height))
            shares.append(both / max(int(inside.sum()), 1))
        views.append(SharedView(images[a], images[b], float(pair_angle), min(shares)))
    return views
