"""Incremental Structure from Motion (COLMAP's incremental mapper in this project's own steps).

Per model: an initial pair from the image graph (`initial_pair`), then repeatedly the unregistered image
with the best visibility pyramid score (`next_image`) registered by P3P in LO-RANSAC and refined
(`geometry.absolute_pose`), with guided 2D-3D matches (`guided`) when its tracks' correspondences fall short,
and checked (`verification`); after each registration its tracks are continued or triangulated, a local BA
adjusts the image and its best-connected neighbours, and the touched points are completed, merged and
filtered. Whenever the model grew by `global_ba_growth`, and at the end, global refinement runs in rounds
(BA -> complete/merge -> filter -> re-triangulate under-reconstructed pairs) until few observations change
(while the model grows, `growth_refinement_rounds`); the last step is a converged global BA. When
registration stalls the thresholds are relaxed once; when a model cannot grow, another is started from
the images no model holds, and moved into the largest model when a verified similarity links them
(`merge`), after which the largest grows on. Orchestration only: the state and its operations live in
`reconstruction.Reconstruction` (the reconstruction being built), the geometry in `geometry/` and `two_view/`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from estimation.bundle_adjustment.factor_graph import IntrinsicsCovariance, IntrinsicsRefinement
from estimation.config import BundleAdjustmentConfig, ReconstructionConfig
from estimation.errors import DegenerateConfigurationError, InputError
from estimation.geometry.absolute_pose import absolute_pose_ransac
from estimation.geometry.pnp import consensus_from_turned_starts, pnp_nonlinear, pnp_ransac
from estimation.geometry.projection import (
    Camera,
    CameraInput,
    as_camera,
    is_shared,
    project,
    transfer_pixels,
)
from estimation.mapper.guided import guided_matches
from estimation.mapper.initial_pair import (
    InitialPairCandidate,
    choose_initial_pair,
    co_visible_pairs,
    pair_name,
)
from estimation.mapper.merge import (
    CrossCorrespondences,
    merge_problem,
    merge_similarity,
    surface_overlap,
)
from estimation.mapper.next_image import PyramidCells, pyramid_cells, visibility_pyramid_scores
from estimation.mapper.reconstruction import Reconstruction
from estimation.mapper.verification import (
    FOLDED,
    LOOSE_ROTATION,
    MIRROR_AMBIGUITY,
    NEAR_MIRROR,
    InlierSupport,
    RotationAgreement,
    VerifiedPair,
    agreement_problem,
    epipolar_share,
    inlier_spread,
    pair_fundamental,
    pose_fundamental,
    pose_rotation_std_deg,
    rotation_agreement,
    rotation_std_problem,
    shared_views,
    support_problem,
    under_intrinsics,
    voting_pairs,
)
from estimation.two_view.geometry import TwoViewGeometry
from estimation.types import CameraPose, ProgressCallback, Tracks

if TYPE_CHECKING:
    from estimation.features.sift import TrackFeatures

FINAL_BA_ROUNDS = 3
"""Converged global BA, filter, and BA again while the filter removed more than a few observations."""

FoldProbe = Callable[[np.ndarray, Camera], bool]
"""Asked after each global refinement of a growing model: is it folded onto itself, given its world-to-camera
rotations (N, 3, 3; NaN where not registered) and its camera (`reconstruct_models`' fold_probe)."""


class FoldedModelError(Exception):
    """A fold probe found the model being built folded onto itself: the mapping stops."""


class ReprojectionSummary(NamedTuple):
    """Reprojection error of the model's observations in pixels."""

    rms_px: float
    mean_px: float
    median_px: float
    num_observations: int


@dataclass
class ReconstructionStats:
    """Numbers for report.json."""

    reprojection_before_ba: ReprojectionSummary  # before the final global refinement
    reprojection_after_ba: ReprojectionSummary
    pair_shared_tracks: dict[str, int]  # "a.png|b.png" -> shared tracks (verified matches)
    initial_pair: tuple[str, str]
    stage_seconds: dict[str, float]
    initial_pair_median_angle_deg: float
    bundle_adjustment_iterations: int  # of the final global BA
    initial_pair_failures: dict[
        str, str
    ]  # candidate pairs tried before this model's pair, and why they failed
    refinement_rounds: int
    relaxed_thresholds: bool  # registration stalled and was retried with relaxed thresholds
    final_cost_decrease: float  # relative robust-cost decrease of the last BA call (~0: converged)
    noise_sigma_px: float  # per-axis pixel noise measured on the final residuals
    reprojection_limit_px: float  # the error limit of the last filter (fixed, or sigmas x noise)
    # 1-sigma of each refined intrinsic of a shared camera at the measured pixel noise (empty: none refined)
    intrinsics_sigma: dict[str, float] = field(default_factory=dict)
    # the refined principal point's shift from where it started, against its covariance (None: held)
    principal_point_test: PrincipalPointTest | None = None
    # other models moved into this one's frame (`_ModelBuilder.merge`): what supported each
    merged_models: list[str] = field(default_factory=list)
    # images registered with guided 2D-3D matches (`_ModelBuilder.guided_correspondences`) -> their inliers
    guided_registrations: dict[str, int] = field(default_factory=dict)
    # each registered image (not the initial pair) -> the rotation std-dev its registration's inliers allowed
    # at 1 px of noise (`verification.pose_rotation_std_deg`), the figure verify_max_rotation_std_deg limits
    registration_rotation_std_deg: dict[str, float] = field(default_factory=dict)


class PrincipalPointTest(NamedTuple):
    """Is the refined principal point's shift from its start significant? d2 = delta^T Sigma^-1 delta."""

    shift_px: tuple[float, float]  # refined - initial (cx, cy)
    sigma_px: tuple[float, float]  # its marginal 1-sigma at the measured noise
    d2: float                      # squared Mahalanobis distance (chi-square, 2 degrees of freedom)
    kept: bool                     # d2 reached CameraConfig.principal_point_min_d2: the refined one stays


class RegistrationCheck(NamedTuple):
    """A registration the verification refused, or a registered image it removed later, and why."""

    image: int
    event: str      # "refused" (at registration) or "removed" (after a global refinement)
    reason: str


@dataclass
class InitialPairDiagnostics:
    """What the figures show about the initial pair (i, j)."""

    i: int
    j: int
    uv_i: np.ndarray  # (K, 2) all putative correspondences
    uv_j: np.ndarray  # (K, 2)
    inlier_mask: np.ndarray  # (K,) inliers of the verified two-view model (E, or F)
    points_linear: np.ndarray  # (L, 3) DLT points of the inliers in front of both cameras
    points_nonlinear: np.ndarray  # (L, 3) the same after non-linear triangulation
    pose_i: CameraPose  # the two cameras in the initial pair's frame (i at the origin)
    pose_j: CameraPose


@dataclass
class SparseModel:
    """Registered cameras and triangulated points with their observations (one model of the set)."""

    image_names: list[str]
    poses: dict[int, CameraPose]  # registered image index -> world-to-camera pose
    unregistered: dict[int, str]  # image index -> why it is not in this model
    points: np.ndarray  # (P, 3)
    point_colors: np.ndarray  # (P, 3) uint8
    point_track_ids: np.ndarray  # (P,) track of each point
    obs_camera: np.ndarray  # (O,) image index
    obs_point: np.ndarray  # (O,) index into points
    obs_uv: np.ndarray  # (O, 2) pixels
    point_errors: np.ndarray  # (P,) mean reprojection error in pixels
    stats: ReconstructionStats
    initial_pair_diagnostics: InitialPairDiagnostics
    registration_order: list[int] = field(default_factory=list)
    cameras: list[Camera] = field(default_factory=list)  # image index -> intrinsics (refined by the BA)
    checks: list[RegistrationCheck] = field(default_factory=list)  # registrations refused or undone
    warnings: list[str] = field(default_factory=list)

    @property
    def visibility(self) -> np.ndarray:
        """(P, M) bool: point p is observed in image m."""
        visible = np.zeros((len(self.points), len(self.image_names)), bool)
        visible[self.obs_point, self.obs_camera] = True
        return visible


def summarize(errors: np.ndarray) -> ReprojectionSummary:
    if len(errors) == 0:
        return ReprojectionSummary(float("nan"), float("nan"), float("nan"), 0)
    return ReprojectionSummary(
        rms_px=float(np.sqrt(np.mean(errors**2))),
        mean_px=float(np.mean(errors)),
        median_px=float(np.median(errors)),
        num_observations=len(errors),
    )


class _Timer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start


class ObservationPairs(NamedTuple):
    """Every pair of observations of one track, and the image pair they link."""

    first: np.ndarray       # (Q,) observation ids
    second: np.ndarray      # (Q,) observation ids, a later one of the same track
    image_pair: np.ndarray  # (Q,) min(m, n) * num_images + max(m, n) of their images m, n


def track_observation_pairs(tracks: Tracks) -> ObservationPairs:
    """The pairs (a, b) of observations sharing a track, a before b: each observation with every later one
    of its track (as a sorted listing), so that per-image-pair counts are one bincount."""
    order = np.argsort(tracks.track_index, kind="stable")
    per_track = np.bincount(tracks.track_index, minlength=tracks.num_tracks)
    track_sorted = tracks.track_index[order]
    later = np.cumsum(per_track)[track_sorted] - np.arange(len(order)) - 1   # of its track, after it
    first = np.repeat(np.arange(len(order)), later)
    offset = np.arange(len(first)) - np.repeat(np.cumsum(later) - later, later)
    first, second = order[first], order[first + 1 + offset]
    image_a, image_b = tracks.image_index[first], tracks.image_index[second]
    num_images = len(tracks.image_names)
    return ObservationPairs(first, second,
                            np.minimum(image_a, image_b) * num_images + np.maximum(image_a, image_b))


def keypoint_sigma(sizes: np.ndarray, reference_px: float) -> np.ndarray:
    """s_o = max(1, size_o / reference_px): the relative pixel std-dev of an observation whose keypoint has
    size_o (its position error grows with the scale it was found at)."""
    return np.maximum(1.0, np.asarray(sizes, float) / reference_px)


@dataclass
class _Thresholds:
    """Registration thresholds of one model; `relax` lowers the inlier minimums once when registration
    stalls. The PnP inlier threshold is never relaxed: the images left at a stall are the weakly seen ones,
    on which a looser threshold lets a wrong pose tie the true one (see relaxed_registration_factor)."""

    min_inliers: float
    min_inlier_ratio: float
    relaxed: bool = False

    def relax(self, factor: float) -> None:
        self.min_inliers *= factor
        self.min_inlier_ratio *= factor
        self.relaxed = True

    def floored(self, min_inliers: float, min_inlier_ratio: float) -> tuple[float, float]:
        """(inliers, ratio) to ask for: relaxed or not, never less than the verification's floor."""
        return max(self.min_inliers, min_inliers), max(self.min_inlier_ratio, min_inlier_ratio)


class _ModelBuilder:
    """Grows one model from its initial pair (orchestration of the Reconstruction's named operations)."""

    def __init__(self, tracks: Tracks, camera: CameraInput, refine: IntrinsicsRefinement,
                 config: ReconstructionConfig, available: np.ndarray, timer: _Timer,
                 progress: ProgressCallback | None, votes: list[list[VerifiedPair]] | None = None,
                 keypoints: TrackFeatures | None = None, fold_probe: FoldProbe | None = None) -> None:
        self.config, self.mapper = config, config.mapper
        self.fold_probe = fold_probe
        # The principal point is refined only from the final global refinement on (`release_principal_point`):
        # while the model grows, its few images cannot determine it, and a drifting one bends what follows.
        self.refine = refine
        staged = config.camera.principal_point_in_final_rounds_only
        self.reconstruction = Reconstruction(tracks, camera,
                           replace(refine, principal_point=refine.principal_point and not staged))
        self.available = available  # images no earlier model holds
        self.timer, self.progress = timer, progress
        self.trials = np.zeros(len(tracks.image_names), np.int64)
        self.failures: dict[int, str] = {}
        self.votes = votes or [[] for _ in tracks.image_names]   # image -> its verified pairs
        self._votes_cameras: list[Camera] | None = None    # the cameras `_current_votes` were taken under
        self._current_votes: dict[int, list[VerifiedPair]] = {}
        self.keypoints = keypoints   # SIFT's keypoints and descriptors: guided matching (None: without)
        self.guided: dict[int, int] = {}   # image registered with guided matches -> their inliers
        self.registered_inliers = np.zeros(len(tracks.image_names), np.int64)
        self.rotation_std = np.full(len(tracks.image_names), np.nan)   # of each registration's inliers
        self.deregistrations = np.zeros(len(tracks.image_names), np.int64)
        self.checks: list[RegistrationCheck] = []
        self.merges: list[str] = []    # other models merged into this one, and their support
        self.thresholds = _Thresholds(self.mapper.min_pnp_inliers, self.mapper.min_pnp_inlier_ratio)
        self.refinement_rounds = 0
        self.error_limit = config.filter.max_reprojection_px
        self.observation_pairs = track_observation_pairs(tracks)
        # Each track observation's pixel std-dev in the final BA, relative (None: all alike).
        reference = self.mapper.final_ba_keypoint_size_px
        self.final_sigma = (None if keypoints is None or reference <= 0 else
                            keypoint_sigma(keypoints.observation_sizes(tracks.image_index), reference))
        # Width and height only bound the visibility pyramid's grid: the principal point is near the centre.
        self.image_size = (2.0 * self.reconstruction.K[0, 2], 2.0 * self.reconstruction.K[1, 2])
        self._cells: PyramidCells | None = None
        self._cells_uv: np.ndarray | None = None   # the working pixels _cells were computed from

    @property
    def tracks(self) -> Tracks:
        """The reconstruction's tracks, in the working pixels of its pinhole K."""
        return self.reconstruction.tracks

    @property
    def max_error(self) -> float:
        """Reprojection limit of triangulation, track completion and filtering (see `measure_noise`)."""
        return self.error_limit

    @property
    def pnp_threshold(self) -> float:
        """min(pnp_threshold_px, pnp_threshold_noise_factor x the reprojection limit): inliers near the
        measured accuracy, so that a wrong pose cannot collect loose ones as easily as the true pose its
        own (factor 0: the fixed pnp_threshold_px only)."""
        fixed, factor = self.config.ransac.pnp_threshold_px, self.mapper.pnp_threshold_noise_factor
        return fixed if factor <= 0 else min(fixed, factor * self.error_limit)

    @property
    def min_angle(self) -> float:
        return self.config.filter.min_triangulation_angle_deg

    # -------------------------------------------------------------------------------------- steps

    def initialize(self, candidate: InitialPairCandidate) -> None:
        g = candidate.geometry
        reconstruction = self.reconstruction
        reconstruction.register_image(g.i, CameraPose(R=np.eye(3), t=np.zeros(3)))
        reconstruction.register_image(g.j, candidate.pose_j)
        keep = candidate.well_conditioned
        track_ids = candidate.track_ids[keep]
        obs_i, obs_j = self._observations_of(g.i, track_ids), self._observations_of(g.j, track_ids)
        index = np.arange(len(track_ids))
        reconstruction.add_points(
            candidate.points[keep], np.concatenate([obs_i, obs_j]), np.concatenate([index, index])
        )
        reconstruction.bundle_adjust(self.refinement_ba_config())
        reconstruction.filter_points(self.max_error, self.min_angle)

    def mapper_ba_config(self, relative_error_tol: float, max_iterations: int,
                         local: bool = False, refining: bool | None = None) -> BundleAdjustmentConfig:
        """The settings of one of the mapper's BAs: mapper_optimizer (mapper_refining_optimizer when it
        refines intrinsics; `refining` None: when the reconstruction's BAs do), stopping at
        relative_error_tol or after max_iterations; a global one eliminates in mapper_global_ordering
        (mapper_refining_global_ordering when it refines intrinsics)."""
        ba = self.config.bundle_adjustment
        refining = self.refines_intrinsics() if refining is None else refining
        optimizer = ba.mapper_refining_optimizer if refining else ba.mapper_optimizer
        update = {"relative_error_tol": relative_error_tol, "optimizer": optimizer,
                  "max_iterations": max_iterations}
        if not local:
            update["ordering"] = ba.mapper_refining_global_ordering if refining else ba.mapper_global_ordering
        return ba.model_copy(update=update)

    def refines_intrinsics(self) -> bool:
        """Whether the reconstruction's BAs refine intrinsics (then its local and refinement BAs take more
        steps)."""
        refine = self.reconstruction.refine
        return refine is not None and refine.refines(self.reconstruction.cameras[0].model)

    def local_refines_intrinsics(self) -> bool:
        """Whether the local BAs refine intrinsics: when the reconstruction's BAs do, per-image cameras
        always (a new image's own camera has only its local BA until the next global refinement), a shared
        one while the model has under local_intrinsics_until_images images (then the global refinements
        and the final BA go on refining it)."""
        if not self.refines_intrinsics():
            return False
        return (self.reconstruction.refine.per_image
                or len(self.reconstruction.order) < self.mapper.local_intrinsics_until_images)

    def local_ba_config(self, refining: bool) -> BundleAdjustmentConfig:
        """A local BA: it stops at local_relative_error_tol or after local_max_iterations
        (local_max_iterations_refining when it refines intrinsics)."""
        ba = self.config.bundle_adjustment
        steps = ba.local_max_iterations_refining if refining else ba.local_max_iterations
        return self.mapper_ba_config(ba.local_relative_error_tol, steps, local=True, refining=refining)

    def refinement_ba_config(self) -> BundleAdjustmentConfig:
        """The global BA of the initial pair and of each refinement round: it stops at
        refinement_relative_error_tol or after refinement_max_iterations (max_iterations when it refines
        intrinsics); the BAs that follow go on."""
        steps = (self.config.bundle_adjustment.max_iterations if self.refines_intrinsics()
                 else self.mapper.refinement_max_iterations)
        return self.mapper_ba_config(self.mapper.refinement_relative_error_tol, steps)

    def measure_noise(self) -> float:
        """After a global BA: error limit = max_reprojection_sigmas x the pixel noise measured on the
        residuals, within [min_reprojection_px, max_reprojection_px], so the filters follow the measurements'
        own accuracy (a fixed limit of a few pixels keeps the mismatches of small images). Returns the
        measured noise sigma (px)."""
        limits = self.config.filter
        sigma = self.reconstruction.noise_sigma(limits.max_reprojection_px)
        self.error_limit = limits.max_reprojection_px
        if limits.max_reprojection_sigmas > 0 and np.isfinite(sigma):
            self.error_limit = float(np.clip(limits.max_reprojection_sigmas * sigma,
                                             limits.min_reprojection_px, limits.max_reprojection_px))
        return sigma

    def _observations_of(self, image: int, track_ids: np.ndarray) -> np.ndarray:
        """Observation id of each given track in `image` (every track must be seen there)."""
        in_image = np.flatnonzero(self.tracks.image_index == image)
        order = np.argsort(self.tracks.track_index[in_image])
        position = np.searchsorted(self.tracks.track_index[in_image][order], track_ids)
        return in_image[order][position]

    def next_images(self) -> list[int]:
        """Unregistered images with enough 2D-3D correspondences, best visibility pyramid score first."""
        reconstruction, tracks = self.reconstruction, self.tracks
        waiting = (self.available & ~reconstruction.registered
                   & (self.trials < self.mapper.max_registration_trials))
        has_point = np.zeros(tracks.num_tracks, bool)
        has_point[reconstruction.point_track[reconstruction.point_alive]] = True
        visible = has_point[tracks.track_index] & waiting[tracks.image_index]
        counts = np.bincount(tracks.image_index[visible], minlength=len(waiting))
        scores = visibility_pyramid_scores(self.pyramid_cells(), len(waiting), visible)
        for image in np.flatnonzero(waiting & (counts < self.mapper.min_pnp_correspondences)):
            self.failures[int(image)] = (
                f"only {counts[image]} 2D-3D correspondences with the reconstructed "
                f"points (need {self.mapper.min_pnp_correspondences})"
            )
        ready = np.flatnonzero(waiting & (counts >= self.mapper.min_pnp_correspondences))
        return [int(m) for m in ready[np.argsort(-scores[ready], kind="stable")]]

    def pyramid_cells(self) -> PyramidCells:
        """Every observation's visibility pyramid cell, again only when the working pixels changed (the
        intrinsics were refined)."""
        if self._cells_uv is not self.tracks.uv:
            self._cells = pyramid_cells(self.tracks.image_index, self.tracks.uv, *self.image_size)
            self._cells_uv = self.tracks.uv
        return self._cells

    def absolute_pose(self, points: np.ndarray, uv: np.ndarray) -> tuple[CameraPose, np.ndarray]:
        """The pose of an image from its 2D-3D correspondences (working pixels) and its inlier mask, at the
        noise-following PnP threshold; DegenerateConfigurationError when there is none."""
        reconstruction = self.reconstruction
        ransac = self.config.ransac.model_copy(update={"pnp_threshold_px": self.pnp_threshold})
        if self.mapper.absolute_pose == "p3p":
            pose = absolute_pose_ransac(reconstruction.K, points, uv, ransac).pose
        else:
            linear = pnp_ransac(reconstruction.K, points, uv, ransac)
            pose = pnp_nonlinear(
                reconstruction.K, points[linear.inlier_mask], uv[linear.inlier_mask], linear.pose
            ).pose
        best = consensus_from_turned_starts(reconstruction.K, points, uv, pose, ransac.pnp_threshold_px,
                                            self.mapper.registration_turn_deg,
                                            self.mapper.registration_turn_min_gain)
        return best.pose, best.inlier_mask

    def support_problem(self, pose: CameraPose, points: np.ndarray, uv: np.ndarray, inliers: np.ndarray
                        ) -> tuple[str | None, float]:
        """Why a pose with these inliers among the 2D-3D correspondences (points, uv) has too weak a
        support (the thresholds, relaxed or not, never under the verification's floor; the rotation they
        determine at 1 px of noise), or None; and that rotation std-dev (deg; NaN when the inlier minimums
        already fail)."""
        min_inliers, min_ratio = self.thresholds.floored(self.mapper.verify_min_inliers,
                                                         self.mapper.verify_min_inlier_ratio)
        support = InlierSupport(int(inliers.sum()), len(uv), inlier_spread(uv[inliers], *self.image_size))
        problem = support_problem(support, min_inliers, min_ratio, self.mapper.verify_min_inlier_spread)
        if problem is not None:
            return problem, np.nan
        std = pose_rotation_std_deg(self.reconstruction.K, pose, points[inliers], 1.0)
        return rotation_std_problem(std, self.mapper.verify_max_rotation_std_deg, support.inliers), std

    def guided_correspondences(self, image: int, pose: CameraPose, point_ids: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray]:
        """(working pixels (G, 2), point ids (G,)): the image's keypoints matched to live points that `pose`
        projects near them (`guided.guided_matches`), without the points of its tracks' correspondences
        (point_ids) and the keypoints behind them."""
        reconstruction, keypoints, sift = self.reconstruction, self.keypoints, self.config.sift
        candidates = np.flatnonzero(reconstruction.point_alive)
        candidates = candidates[~np.isin(candidates, point_ids)]
        projection = project(reconstruction.K, pose.R, pose.t, reconstruction.point_xyz[candidates])
        width, height = self.image_size
        inside = ((projection.depth > 0) & (projection.uv >= 0).all(axis=1)
                  & (projection.uv[:, 0] < width) & (projection.uv[:, 1] < height))
        candidates, projected = candidates[inside], projection.uv[inside]
        used = reconstruction.used_observations()
        position = np.full(len(reconstruction.point_alive), -1, np.int64)
        position[candidates] = np.arange(len(candidates))
        used = used[position[reconstruction.obs_point[used]] >= 0]
        own = keypoints.observation_keypoint[reconstruction.correspondences_2d3d(image)[0]]
        free = np.setdiff1d(np.arange(len(keypoints.images[image].uv)), own)
        keypoint_uv = transfer_pixels(reconstruction.cameras[image], Camera.from_K(reconstruction.K),
                                      keypoints.images[image].uv[free])
        matches = guided_matches(projected, position[reconstruction.obs_point[used]],
                                 keypoints.observation_descriptors(used, self.tracks.image_index[used]),
                                 keypoint_uv,
                                 keypoints.images[image].descriptors[free], self.mapper.guided_radius_px,
                                 sift.ratio, sift.max_distance)
        return keypoint_uv[matches.keypoints], candidates[matches.points]

    def register(self, image: int) -> str | None:
        """`try_register`; a refusal for a loosely pinned rotation is also listed in the checks (report.json's
        registration_checks), as the rotation vote's are: it is where a wrong placement was avoided."""
        reason = self.try_register(image)
        if reason is not None and LOOSE_ROTATION in reason:
            self.checks.append(RegistrationCheck(image, "refused", reason))
        return reason

    def try_register(self, image: int) -> str | None:
        """Absolute pose of `image` from its 2D-3D correspondences (with guided ones when its tracks' alone
        are too few, `guided_correspondences`), held to the registration checks; adds its inlier
        observations to their points. Returns why it failed, or None."""
        reconstruction = self.reconstruction
        obs_ids, point_ids = reconstruction.correspondences_2d3d(image)
        points, uv = reconstruction.point_xyz.take(point_ids, axis=0), self.tracks.uv.take(obs_ids, axis=0)
        try:
            pose, inliers = self.absolute_pose(points, uv)
        except DegenerateConfigurationError as error:
            return str(error)
        problem, rotation_std = self.support_problem(pose, points, uv, inliers)
        if problem is not None and self.keypoints is not None and self.mapper.guided_matching:
            guided_uv, guided_points = self.guided_correspondences(image, pose, point_ids)
            if len(guided_points):
                all_uv = np.concatenate([uv, guided_uv])
                all_points = np.concatenate([points, reconstruction.point_xyz[guided_points]])
                try:
                    pose, inliers = self.absolute_pose(all_points, all_uv)
                except DegenerateConfigurationError as error:
                    return f"{problem}; with {len(guided_points)} guided 2D-3D matches: {error}"
                guided_problem, rotation_std = self.support_problem(pose, all_points, all_uv, inliers)
                guided_inliers = int(inliers[len(obs_ids):].sum())
                if guided_problem is None and guided_inliers < self.mapper.guided_min_inliers:
                    guided_problem = (f"{guided_inliers} of its inliers are guided matches (need "
                                      f"{self.mapper.guided_min_inliers})")
                if guided_problem is not None:
                    return f"{problem}; with {len(guided_points)} guided 2D-3D matches: {guided_problem}"
                problem = None
                self.guided[image] = guided_inliers
                inliers = inliers[:len(obs_ids)]
        if problem is None:
            problem = agreement_problem(self.rotation_agreement(image, pose),
                                        self.mapper.verify_min_rotation_agreement, self.tracks.image_names)
            if problem is not None:
                self.checks.append(RegistrationCheck(image, "refused", problem))
        if problem is not None:
            self.guided.pop(image, None)
            return problem
        reconstruction.register_image(image, pose)
        reconstruction.add_observations(obs_ids[inliers], point_ids[inliers])
        self.registered_inliers[image] = int(inliers.sum())   # its observations (guided matches are not)
        self.rotation_std[image] = rotation_std
        return None

    def current_votes(self, image: int) -> list[VerifiedPair]:
        """The image's verified pairs, those resting on F under the model's current intrinsics (refined by
        the global BAs when self-calibrating) rather than the initial prior, and only where they are
        consistent with them (`under_intrinsics`); kept until the cameras change."""
        cameras = self.reconstruction.cameras
        if self._votes_cameras is not cameras:
            self._votes_cameras, self._current_votes = cameras, {}
        if image not in self._current_votes:
            min_ratio = self.mapper.verify_min_essential_singular_ratio
            current = (under_intrinsics(pair, cameras[image].K, cameras[pair.other].K, min_ratio)
                       for pair in self.votes[image])
            self._current_votes[image] = [pair for pair in current if pair is not None]
        return self._current_votes[image]

    def rotation_agreement(self, image: int, pose: CameraPose) -> RotationAgreement:
        """How the pose of `image` agrees with its verified pairs with the other registered images; a
        disagreeing pair votes only when their track correspondences contradict the pose (`contradicts`)."""
        reconstruction = self.reconstruction
        pairs = [pair for pair in self.current_votes(image)
                 if reconstruction.registered[pair.other] and pair.other != image]
        R_of = {pair.other: reconstruction.R[pair.other] for pair in pairs}
        max_deviation = self.mapper.verify_max_rotation_deviation_deg
        agreement = rotation_agreement(pose.R, pairs, R_of, max_deviation)
        if agreement.share >= 1.0:
            return agreement
        credible = [pair for pair in pairs if agreement.deviations_deg[pair.other] <= max_deviation
                    or self.contradicts(image, pose, pair)]
        return rotation_agreement(pose.R, credible, R_of, max_deviation)

    def contradicts(self, image: int, pose: CameraPose, pair: VerifiedPair) -> bool:
        """Whether the pose of `image` explains under verify_veto_support_ratio times the share of their track
        correspondences that the pair's own geometry explains (`epipolar_share` at the PnP threshold); True
        without correspondences (the pair's E is then the only evidence)."""
        reconstruction = self.reconstruction
        _, uv_image, uv_other = self.tracks.pair_correspondences(image, pair.other)   # working pixels of K
        if len(uv_image) == 0:
            return True
        own = epipolar_share(pair_fundamental(pair, reconstruction.K), uv_image, uv_other, self.pnp_threshold)
        posed = epipolar_share(pose_fundamental(reconstruction.K, pose, reconstruction.pose(pair.other)),
                               uv_image, uv_other, self.pnp_threshold)
        return posed < self.mapper.verify_veto_support_ratio * own

    def cross_correspondences(self, other: Reconstruction) -> CrossCorrespondences:
        """This model's keypoints (in its registered images) whose tracks have a point in `other`."""
        reconstruction = self.reconstruction
        obs_ids, point_ids = [], []
        for image in reconstruction.order:
            image_obs, image_points = other.correspondences_2d3d(image)
            obs_ids.append(image_obs)
            point_ids.append(image_points)
        obs, points = np.concatenate(obs_ids), np.concatenate(point_ids)
        images = self.tracks.image_index[obs]
        return CrossCorrespondences(reconstruction.R[images], reconstruction.t[images], self.tracks.uv[obs],
                                    other.point_xyz[points])

    def merge(self, other: _ModelBuilder) -> tuple[list[int], str]:
        """Move the other model into this one's frame when a similarity puts enough of the points of each
        onto the keypoints of the other's images (`merge.merge_similarity`) and every moved image's rotation
        agrees with its verified pairs; then refine globally. Returns (the images added, what was found)."""
        first, second = self.reconstruction, other.reconstruction
        point_first, point_second = first.main_point_of_track(), second.main_point_of_track()
        shared = np.flatnonzero((point_first >= 0) & (point_second >= 0))
        ransac = self.config.ransac
        merge = merge_similarity(second.point_xyz[point_second[shared]],
                                 first.point_xyz[point_first[shared]], first.K,
                                 self.cross_correspondences(second), other.cross_correspondences(first),
                                 self.pnp_threshold, ransac.max_iterations, ransac.seed, ransac.local_refits)
        overlap = 0.0 if merge is None else surface_overlap(
            merge.similarity.apply_points(second.point_xyz[second.point_alive]),
            first.point_xyz[first.point_alive], self.mapper.merge_overlap_spacings)
        problem = merge_problem(merge, overlap, self.mapper.merge_min_inliers, self.mapper.merge_min_overlap)
        if problem is not None:
            return [], problem
        moved = {image: merge.similarity.apply_pose(second.pose(image)).R for image in second.order}
        R_of = {**{image: first.R[image] for image in first.order}, **moved}
        K_of = {**{image: first.cameras[image].K for image in first.order},
                **{image: second.cameras[image].K for image in second.order}}
        for image, R in moved.items():
            current = (under_intrinsics(pair, K_of[image], K_of[pair.other],
                                        self.mapper.verify_min_essential_singular_ratio)
                       for pair in self.votes[image] if pair.other in R_of and pair.other != image)
            pairs = [pair for pair in current if pair is not None]
            agreement = rotation_agreement(R, pairs, {pair.other: R_of[pair.other] for pair in pairs},
                                           self.mapper.verify_max_rotation_deviation_deg)
            problem = agreement_problem(agreement, self.mapper.verify_min_rotation_agreement,
                                        self.tracks.image_names)
            if problem is not None:
                return [], f"{self.tracks.image_names[image]} would be moved, but {problem}"
        added = first.absorb(second, merge.similarity)
        self.available[added] = True
        # Deregistered after the refinement below when it filters away most of what the other model saw.
        used = second.used_observations()
        self.registered_inliers[added] = np.bincount(self.tracks.image_index[used],
                                                     minlength=len(first.registered))[added]
        self.rotation_std[added] = other.rotation_std[added]
        found = (f"{len(added)} images merged by a similarity that reprojects {merge.inliers} of "
                 f"{merge.correspondences} cross-model 2D-3D correspondences (from {merge.shared_points} "
                 f"shared points; {overlap:.0%} of the moved points on this model's surface)")
        # The cross-model links at the merge's own threshold, for the BA to close the seam (filtered after).
        first.complete_tracks(self.pnp_threshold)
        first.merge_tracks(self.pnp_threshold)
        self.global_refinement(self.mapper.refinement_max_rounds)
        self.verify_registered()
        return added, found

    def verify_registered(self) -> list[int]:
        """After a global refinement: remove the images (not the initial pair) whose observations were mostly
        filtered away (below deregister_min_kept_ratio of their registration's inliers) or whose rotation
        no longer agrees with their verified pairs; each may be tried again up to max_deregistrations
        times. Returns the images removed."""
        reconstruction, mapper = self.reconstruction, self.mapper
        used = reconstruction.used_observations()
        kept = np.bincount(self.tracks.image_index[used], minlength=len(reconstruction.registered))
        removed = []
        for image in reconstruction.order[2:]:
            reason = None
            if kept[image] < mapper.deregister_min_kept_ratio * self.registered_inliers[image]:
                reason = (f"{kept[image]} of its observations survived the filters, registered with "
                          f"{self.registered_inliers[image]} inliers "
                          f"(need {mapper.deregister_min_kept_ratio:.0%})")
            else:
                reason = agreement_problem(self.rotation_agreement(image, reconstruction.pose(image)),
                                           mapper.verify_min_rotation_agreement, self.tracks.image_names)
            if reason is not None:
                removed.append(image)
                self.checks.append(RegistrationCheck(image, "removed", reason))
                self.failures[image] = f"removed after a global refinement: {reason}"
        for image in removed:
            reconstruction.deregister_image(image)
            self.deregistrations[image] += 1
            if self.deregistrations[image] <= mapper.max_deregistrations:
                self.trials[image] = 0
            else:
                self.trials[image] = mapper.max_registration_trials
        return removed

    def triangulate_image(self, image: int) -> None:
        """New points for the image's tracks without one. Existing points need no completion here: the
        registration added the image's observations within the PnP threshold (at least the reprojection
        limit) to them, and the local BA's completion follows (a completion of every track here added 0-1
        observations per lego mapping, for 60 ms)."""
        tracks = self.tracks
        image_tracks = tracks.track_index[tracks.image_index == image]
        self.reconstruction.triangulate_tracks(
            image_tracks, self.max_error, self.min_angle, self.mapper.triangulation_hypotheses
        )

    def local_bundle_adjustment(self, image: int) -> None:
        """BA of `image` and the local_window - 1 images sharing most points with it; then complete, merge
        and filter the points they see."""
        reconstruction = self.reconstruction
        used = reconstruction.used_observations()
        own = reconstruction.points_seen_in([image])
        shared = np.bincount(self.tracks.image_index[used[own[reconstruction.obs_point[used]]]],
                             minlength=len(reconstruction.registered))
        shared[image] = 0
        ba = self.config.bundle_adjustment
        neighbours = np.argsort(-shared, kind="stable")[: ba.local_window - 1]
        window = [image, *[int(m) for m in neighbours if shared[m] > 0]]
        refining = self.local_refines_intrinsics()
        reconstruction.bundle_adjust(self.local_ba_config(refining), variable_images=window,
                                     hold_intrinsics=not refining)
        touched = np.flatnonzero(reconstruction.points_seen_in(window))
        reconstruction.complete_tracks(self.max_error, touched)
        reconstruction.merge_tracks(self.max_error)
        reconstruction.filter_points(self.max_error, self.min_angle, touched)

    def retriangulate(self) -> int:
        """Triangulate again the untriangulated tracks of registered image pairs whose shared tracks are
        less than retriangulation_min_ratio triangulated (poses have improved, images were added).
        Returns the points added."""
        reconstruction, tracks, pairs = self.reconstruction, self.tracks, self.observation_pairs
        num_images = len(reconstruction.registered)
        registered = reconstruction.registered[tracks.image_index]
        used = reconstruction.obs_point >= 0
        both_registered = registered[pairs.first] & registered[pairs.second]
        # A track seen in both images of a pair adds one observation pair to it (one observation per image).
        shared = np.bincount(pairs.image_pair[both_registered], minlength=num_images**2)
        triangulated = np.bincount(pairs.image_pair[both_registered & used[pairs.first] & used[pairs.second]],
                                   minlength=num_images**2)
        under = (shared > 0) & (triangulated / np.maximum(shared, 1) < self.mapper.retriangulation_min_ratio)
        if not under.any():
            return 0
        # A track qualifies when two of its registered images form an under-reconstructed pair.
        candidates = np.zeros(tracks.num_tracks, bool)
        candidates[tracks.track_index[pairs.first[both_registered & under[pairs.image_pair]]]] = True
        return reconstruction.triangulate_tracks(
            np.flatnonzero(candidates), self.max_error, self.min_angle, self.mapper.triangulation_hypotheses
        )

    def global_refinement(self, max_rounds: int) -> float:
        """Up to max_rounds rounds of global BA (to refinement_relative_error_tol) -> complete and merge
        tracks -> filter -> re-triangulate, until fewer than refinement_min_change of the observations
        changed, or until a later round's BA finds the model already near its optimum (relative decrease
        below that tolerance: what the previous round changed did not move it, and the filters would act
        on the same model again). Returns the last BA's relative cost decrease."""
        reconstruction = self.reconstruction
        ba_config = self.refinement_ba_config()
        decrease = 0.0
        for round_ in range(max_rounds):
            before = len(reconstruction.used_observations())
            result = reconstruction.bundle_adjust(ba_config)
            decrease = (result.initial_cost - result.final_cost) / max(result.initial_cost, 1e-300)
            if round_ > 0 and decrease < ba_config.relative_error_tol:
                break
            self.measure_noise()
            changed = (reconstruction.complete_tracks(self.max_error)
                       + reconstruction.merge_tracks(self.max_error))
            changed += reconstruction.filter_points(self.max_error, self.min_angle)
            changed += self.retriangulate()
            self.refinement_rounds += 1
            if changed <= self.mapper.refinement_min_change * max(before, 1):
                break
        return decrease

    def final_bundle_adjustment(self) -> tuple[float, int, IntrinsicsCovariance | None]:
        """Converged global BA (tight tolerance; each observation weighed by its keypoint's size,
        `final_sigma`), filtering and adjusting again while the filter removes more than final_min_change
        of the observations. Returns (relative cost decrease of the last BA, its iterations, the
        covariance of the refined shared intrinsics at the measured pixel noise)."""
        ba = self.config.bundle_adjustment
        final = self.mapper_ba_config(min(ba.relative_error_tol, self.mapper.final_relative_error_tol),
                                      ba.max_iterations)
        decrease, iterations, covariance = 0.0, 0, None
        for _ in range(FINAL_BA_ROUNDS):
            result = self.reconstruction.bundle_adjust(final, intrinsics_covariance=True,
                                                       relative_sigma=self.final_sigma)
            decrease = (result.initial_cost - result.final_cost) / max(result.initial_cost, 1e-300)
            iterations = result.iterations
            # The filter's limit follows the measured noise; so does the BA's covariance, which is for
            # measurement_sigma_px of noise.
            noise = self.measure_noise() / ba.measurement_sigma_px
            covariance = result.intrinsics_covariance and result.intrinsics_covariance.scaled(noise)
            observations = len(self.reconstruction.used_observations())
            # The weighted BA fits a coarse keypoint to its own std-dev: so does the filter.
            removed = self.reconstruction.filter_points(self.max_error, self.min_angle,
                                                        relative_sigma=self.final_sigma,
                                                        ceiling_px=self.config.filter.max_reprojection_px)
            if removed <= self.mapper.final_min_change * observations:
                break
        return decrease, iterations, covariance

    def mirror_warnings(self) -> list[str]:
        """Warnings of near-mirror ambiguity: images whose verified pairs disagree with their final rotation,
        images refused or removed for such a disagreement during the reconstruction, and a model folded
        onto itself (`fold_warning`)."""
        names = self.tracks.image_names
        warnings = []
        for image in self.reconstruction.order:
            problem = agreement_problem(self.rotation_agreement(image, self.reconstruction.pose(image)),
                                        self.mapper.verify_min_rotation_agreement, names)
            if problem is not None:
                warnings.append(f"{MIRROR_AMBIGUITY}: {names[image]} is registered, but {problem}")
        flipped = sorted({names[check.image] for check in self.checks if NEAR_MIRROR in check.reason})
        if flipped:
            warnings.append(f"{MIRROR_AMBIGUITY}: {len(flipped)} image(s) matched a pose on the other "
                            f"side of the object and were refused or removed at least once "
                            f"({', '.join(flipped)}); symmetric objects need views that overlap their "
                            "neighbours well")
        folded = self.fold_warning()
        if folded is not None:
            warnings.append(folded)
        return warnings

    def fold_warning(self) -> str | None:
        """A warning when at least fold_min_pairs pairs of cameras placed within fold_max_angle_deg of one
        viewpoint share under fold_min_shared of their points (`shared_views`): a symmetric object's far side
        put at the near side's viewpoints by its look-alike features. Which side is the true one, the points
        cannot tell."""
        mapper, reconstruction, names = self.mapper, self.reconstruction, self.tracks.image_names
        if mapper.fold_min_shared <= 0:
            return None
        used = reconstruction.used_observations()
        views = shared_views(reconstruction.poses, reconstruction.cameras, self.image_size,
                             reconstruction.point_xyz, self.tracks.image_index[used],
                             reconstruction.obs_point[used], mapper.fold_max_angle_deg)
        folded = sorted((view for view in views if view.shared < mapper.fold_min_shared),
                        key=lambda view: view.shared)
        if len(folded) < mapper.fold_min_pairs:
            return None
        pairs = ", ".join(f"{names[view.image_a]} and {names[view.image_b]} {view.shared:.0%}"
                          for view in folded)
        return (f"{FOLDED}: {len(folded)} pairs of cameras placed "
                f"within {mapper.fold_max_angle_deg:g} deg of one viewpoint observe under "
                f"{mapper.fold_min_shared:.0%} of the points they should share ({pairs}); cameras of the far "
                "side may sit at the near side's viewpoints")

    def test_principal_point(self, covariance: IntrinsicsCovariance | None) -> PrincipalPointTest | None:
        """The refined principal point's shift from its start (the image centre) against its covariance;
        None when it was not refined."""
        if covariance is None or "cx" not in covariance.names:
            return None
        camera = self.reconstruction.cameras[self.reconstruction.order[0]]
        shift = np.array([camera.cx - self.reconstruction.K[0, 2], camera.cy - self.reconstruction.K[1, 2]])
        block = covariance.block(("cx", "cy"))
        d2 = float(shift @ np.linalg.solve(block, shift))
        sigma = np.sqrt(np.diag(block))
        return PrincipalPointTest((float(shift[0]), float(shift[1])), (float(sigma[0]), float(sigma[1])), d2,
                                  d2 >= self.config.camera.principal_point_min_d2)

    def release_principal_point(self) -> None:
        """From now on, refine the principal point if asked for (the final rounds)."""
        self.reconstruction.refine = replace(self.reconstruction.refine,
                                             principal_point=self.refine.principal_point)

    def hold_principal_point(self) -> None:
        """Put the principal point back where it started and hold it in every later BA."""
        reconstruction = self.reconstruction
        reconstruction.refine = replace(reconstruction.refine, principal_point=False)
        centred = replace(reconstruction.cameras[reconstruction.order[0]], cx=reconstruction.K[0, 2],
                          cy=reconstruction.K[1, 2])
        reconstruction.use_cameras([centred] * len(reconstruction.cameras))

    # -------------------------------------------------------------------------------------- loop

    def refine_growing_model(self) -> None:
        """A global refinement of the growing model and the check of its registrations, then the fold probe:
        FoldedModelError when it finds the model folded (given its world-to-camera rotations, NaN where not
        registered, and its camera)."""
        with self.timer.stage("global refinement"):
            self.global_refinement(self.mapper.growth_refinement_rounds)
            self.verify_registered()
        reconstruction = self.reconstruction
        if self.fold_probe is not None and self.fold_probe(reconstruction.R.copy(),
                                                           reconstruction.cameras[reconstruction.order[0]]):
            raise FoldedModelError(f"the model of {len(reconstruction.order)} images is folded onto itself")

    def grow(self, num_images: int, images_done: int) -> None:
        """Register images until none more can be: each success triangulates and adjusts; a stall
        relaxes the thresholds once (after a global refinement that may add 2D-3D correspondences)."""
        last_global = len(self.reconstruction.order)
        while True:
            registered = None
            for image in self.next_images():
                if self.progress:
                    self.progress(
                        f"register {self.tracks.image_names[image]}",
                        min(0.9, 0.05 + 0.85 * (images_done + len(self.reconstruction.order)) / num_images),
                    )
                with self.timer.stage("registration"):
                    reason = self.register(image)
                self.trials[image] += 1
                if reason is None:
                    registered = image
                    self.failures.pop(image, None)
                    break
                self.failures[image] = reason
            if registered is None:
                if self.thresholds.relaxed or not (self.available & ~self.reconstruction.registered).any():
                    return
                self.refine_growing_model()
                self.thresholds.relax(self.mapper.relaxed_registration_factor)
                self.trials[:] = 0
                continue
            with self.timer.stage("triangulation"):
                self.triangulate_image(registered)
            with self.timer.stage("local bundle adjustment"):
                self.local_bundle_adjustment(registered)
            if len(self.reconstruction.order) >= self.mapper.global_ba_growth * last_global:
                self.refine_growing_model()
                last_global = len(self.reconstruction.order)


# ----------------------------------------------------------------------------------------------------


def _sparse_model(
    builder: _ModelBuilder, candidate: InitialPairCandidate, stats: ReconstructionStats
) -> SparseModel:
    reconstruction, tracks = builder.reconstruction, builder.tracks
    used = reconstruction.used_observations()
    point_ids, obs_point = np.unique(reconstruction.obs_point[used], return_inverse=True)
    errors = reconstruction.errors(used)
    point_errors = np.bincount(obs_point, weights=errors, minlength=len(point_ids)) / np.maximum(
        np.bincount(obs_point, minlength=len(point_ids)), 1
    )
    g = candidate.geometry
    diagnostics = InitialPairDiagnostics(
        i=g.i,
        j=g.j,
        uv_i=g.uv_i,
        uv_j=g.uv_j,
        inlier_mask=g.inlier_mask,
        points_linear=candidate.points_linear,
        points_nonlinear=candidate.points,
        pose_i=CameraPose(R=np.eye(3), t=np.zeros(3)),
        pose_j=candidate.pose_j,
    )
    track_ids = reconstruction.point_track[point_ids]
    return SparseModel(
        image_names=list(tracks.image_names),
        poses=reconstruction.poses,
        unregistered={},
        points=reconstruction.point_xyz[point_ids].copy(),
        point_colors=tracks.colors[track_ids],
        point_track_ids=track_ids,
        obs_camera=tracks.image_index[used].copy(),
        obs_point=obs_point,
        obs_uv=reconstruction.observed_uv[used].copy(),
        point_errors=point_errors,
        stats=stats,
        initial_pair_diagnostics=diagnostics,
        registration_order=list(reconstruction.order),
        cameras=list(reconstruction.cameras),
    )


def _why_no_model(
    tracks: Tracks,
    pairs: list[tuple[int, int, int]],
    failures: dict[tuple[int, int], str],
    small_models: dict[tuple[int, int], str],
) -> str:
    """One line per image: why no model could start from (or hold) it."""
    lines = []
    for m, name in enumerate(tracks.image_names):
        own = [(i, j, n) for i, j, n in pairs if m in (i, j)]
        if not own:
            lines.append(f"{name}: shares no track with any other image")
            continue
        i, j, n = max(own, key=lambda pair: pair[2])
        reason = small_models.get((i, j)) or failures.get((i, j)) or "not tried"
        lines.append(f"{name}: best pair {pair_name(tracks, i, j)} ({n} shared tracks): {reason}")
    return "no model could be started:\n" + "\n".join(lines)


def _finished_model(builder: _ModelBuilder, candidate: InitialPairCandidate,
                    initial_pair_failures: dict[str, str], pair_shared: dict[str, int], num_images: int,
                    available: np.ndarray,
                    progress: ProgressCallback | None) -> SparseModel:
    """The final global refinement of a grown model (images removed by it are tried again once), its
    converged BA with the principal point test, and the model with its statistics."""
    mapper, timer, reconstruction = builder.mapper, builder.timer, builder.reconstruction
    if progress:
        done = num_images - available.sum() + len(reconstruction.order)
        progress("bundle adjustment", min(0.9, 0.05 + 0.85 * done / num_images))
    before = summarize(reconstruction.errors(reconstruction.used_observations()))
    with timer.stage("bundle adjustment"):
        builder.release_principal_point()
        builder.global_refinement(mapper.refinement_max_rounds)
        if builder.verify_registered():
            builder.grow(num_images, num_images - int(available.sum()))
            builder.global_refinement(mapper.refinement_max_rounds)
        decrease, iterations, covariance = builder.final_bundle_adjustment()
        principal_point_test = builder.test_principal_point(covariance)
        if principal_point_test is not None and not principal_point_test.kept:
            # Not determined beyond its noise: the image centre is the better guess (model selection).
            builder.hold_principal_point()
            decrease, iterations, covariance = builder.final_bundle_adjustment()
    after = summarize(reconstruction.errors(reconstruction.used_observations()))
    tracks, config = builder.tracks, builder.config
    pair = (candidate.geometry.i, candidate.geometry.j)
    stats = ReconstructionStats(
        reprojection_before_ba=before,
        reprojection_after_ba=after,
        pair_shared_tracks=pair_shared,
        initial_pair=(tracks.image_names[pair[0]], tracks.image_names[pair[1]]),
        stage_seconds=timer.seconds,
        initial_pair_median_angle_deg=candidate.median_angle_deg,
        bundle_adjustment_iterations=iterations,
        initial_pair_failures=initial_pair_failures,
        refinement_rounds=builder.refinement_rounds,
        relaxed_thresholds=builder.thresholds.relaxed,
        final_cost_decrease=decrease,
        noise_sigma_px=reconstruction.noise_sigma(config.filter.max_reprojection_px),
        reprojection_limit_px=builder.error_limit,
        intrinsics_sigma=covariance.sigma() if covariance is not None else {},
        principal_point_test=principal_point_test,
        merged_models=list(builder.merges),
        guided_registrations={tracks.image_names[image]: inliers for image, inliers in builder.guided.items()
                              if reconstruction.registered[image]},
        registration_rotation_std_deg={tracks.image_names[image]: float(builder.rotation_std[image])
                                       for image in reconstruction.order
                                       if np.isfinite(builder.rotation_std[image])},
    )
    model = _sparse_model(builder, candidate, stats)
    model.checks, model.warnings = list(builder.checks), builder.mirror_warnings()
    return model


def never_back(progress: ProgressCallback) -> ProgressCallback:
    """`progress` with each fraction raised to the largest reported before: a later model starts where the
    earlier one's final adjustment ended, not at the share of images its start counts."""
    reached = 0.0

    def report(stage: str, fraction: float) -> None:
        nonlocal reached
        reached = max(reached, float(fraction))
        progress(stage, reached)
    return report


def reconstruct_models(
    tracks: Tracks,
    camera: CameraInput,
    config: ReconstructionConfig,
    progress: ProgressCallback | None = None,
    refine: IntrinsicsRefinement = IntrinsicsRefinement(),
    pair_types: dict[tuple[int, int], str] | None = None,
    pair_geometries: dict[tuple[int, int], TwoViewGeometry] | None = None,
    keypoints: TrackFeatures | None = None,
    fold_probe: FoldProbe | None = None,
) -> list[SparseModel]:
    """Every model incremental SfM can build from the tracks, largest first.

    A model starts from the best initial pair among images no earlier model holds and grows until no
    image registers; models under min_model_images are discarded (their pair is not tried again).
    `pair_types` maps (i, j), i < j, to geometric verification's label; planar/panoramic pairs never start
    a model. `pair_geometries` (the verified geometry of each pair, by (i, j)) lets each registration be
    checked against its pairs' relative rotations (`verification`); `keypoints` (SIFT's keypoints and
    descriptors behind the tracks) lets an image that failed be matched again against the model
    (`guided`). `camera` (a 3x3 K, a Camera, or one
    Camera per image) is every image's initial camera; each global BA refines the intrinsics as `refine`
    says, and the models' `cameras` carry the result. `fold_probe`, asked after each global refinement,
    stops the mapping with FoldedModelError when it finds the growing model folded. `progress` never goes
    back (`never_back`).
    Raises DegenerateConfigurationError naming, per image, why no model could start.
    """
    num_images = len(tracks.image_names)
    if num_images < 2:
        raise InputError(f"Structure from Motion needs at least 2 images, got {num_images}")
    progress = never_back(progress) if progress else None
    first_camera = as_camera(camera) if is_shared(camera) else camera[0]
    K = first_camera.pinhole().K
    mapper = config.mapper
    timer = _Timer()
    pairs = co_visible_pairs(tracks)
    pair_shared = {pair_name(tracks, i, j): n for i, j, n in pairs}
    available = np.ones(num_images, bool)
    failures: dict[tuple[int, int], str] = {}
    small_models: dict[tuple[int, int], str] = {}
    min_images = min(mapper.min_model_images, num_images)
    built: list[tuple[_ModelBuilder, SparseModel]] = []
    starts: list[tuple[InitialPairCandidate, dict[str, str]]] = []   # of each built model
    votes = voting_pairs(pair_geometries or {}, num_images, mapper.verify_pair_min_inliers)
    while len(built) < mapper.max_models and available.sum() >= 2:
        if progress:
            progress("initial pair", 0.02 + 0.85 * (num_images - available.sum()) / num_images)
        untried = [
            (i, j, n)
            for i, j, n in pairs
            if available[i] and available[j] and (i, j) not in failures and (i, j) not in small_models
        ]
        with timer.stage("initial pair"):
            choice = choose_initial_pair(K, tracks, untried, config, pair_types)
        new_failures = {pair_name(tracks, *pair): reason for pair, reason in choice.failures.items()}
        failures.update(choice.failures)
        if choice.candidate is None:
            break
        candidate = choice.candidate
        builder = _ModelBuilder(tracks, camera, refine, config, available.copy(), timer, progress, votes,
                                keypoints, fold_probe)
        with timer.stage("initial pair"):
            builder.initialize(candidate)
        builder.grow(num_images, num_images - int(available.sum()))
        pair = (candidate.geometry.i, candidate.geometry.j)
        if len(builder.reconstruction.order) < min_images:
            small_models[pair] = (
                f"the model it started could register only {len(builder.reconstruction.order)} "
                f"images (need {min_images}, min_model_images)"
            )
            continue
        merge_refusal = None
        if built and mapper.merge_models:
            index = max(range(len(built)), key=lambda k: len(built[k][0].reconstruction.order))
            largest, (first_candidate, first_failures) = built[index][0], starts[index]
            with timer.stage("model merge"):
                added, found = largest.merge(builder)
            if added:
                largest.merges.append(found)
                largest.available = available | largest.reconstruction.registered
                largest.trials[:] = 0
                largest.grow(num_images, num_images - int(available.sum()))
                built[index] = (largest, _finished_model(largest, first_candidate, first_failures,
                                                         pair_shared, num_images, available, progress))
                available[largest.reconstruction.order] = False
                continue
            merge_refusal = f"not merged into the largest model: {found}"
        model = _finished_model(builder, candidate, new_failures, pair_shared, num_images, available,
                                progress)
        if merge_refusal is not None:
            model.warnings.append(merge_refusal)
        available[builder.reconstruction.order] = False
        built.append((builder, model))
        starts.append((candidate, new_failures))
    if not built:
        raise DegenerateConfigurationError(_why_no_model(tracks, pairs, failures, small_models))
    if progress:
        progress("done", 1.0)
    built.sort(key=lambda item: -len(item[1].poses))
    models = [model for _, model in built]
    for builder, model in built:
        for m in range(num_images):
            if m in model.poses:
                continue
            holder = next((n for n, other in enumerate(models) if m in other.poses), None)
            if holder is not None:
                model.unregistered[m] = (
                    f"registered in model {holder + 1} ({len(models[holder].poses)} images)"
                )
            else:
                model.unregistered[m] = builder.failures.get(m) or next(
                    (b.failures[m] for b, _ in built if m in b.failures), "shares no registered point"
                )
    return models


def run_incremental(tracks: Tracks, camera: CameraInput, config: ReconstructionConfig,
                    progress: ProgressCallback | None = None,
                    refine: IntrinsicsRefinement = IntrinsicsRefinement()) -> SparseModel:
    """The largest model of `reconstruct_models` (the others are named in its `unregistered` reasons)."""
    return reconstruct_models(tracks, camera, config, progress, refine)[0]
