"""Incremental Structure from Motion: an initial pair, then one image at a time, local and global BA.

Orchestration only: the geometry lives in fundamental / essential / triangulation / pnp, the
optimization in bundle_adjustment. The model under construction is indexed by track: track t has a
3D point when `has_point[t]`, and flat observation o of `tracks` is part of the model when `obs_used[o]`.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from scipy import sparse

from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement
from estimation.config import ReconstructionConfig
from estimation.errors import DegenerateConfigurationError, InputError
from estimation.geometry.pnp import pnp_nonlinear, pnp_ransac, reprojection_errors
from estimation.geometry.projection import Camera, CameraInput, as_camera, is_shared, transfer_pixels
from estimation.geometry.triangulation import (
    Observations,
    observations_for_pair,
    reprojection_residuals,
    triangulate_linear,
    triangulate_nonlinear,
    triangulation_angle_deg,
)
from estimation.two_view.essential import choose_relative_pose, essential_from_fundamental
from estimation.two_view.fundamental import MIN_CORRESPONDENCES as MIN_F_CORRESPONDENCES
from estimation.two_view.fundamental import FundamentalResult, ransac_fundamental
from estimation.types import CameraPose, ProgressCallback, Tracks

ROBUST_TRIANGULATION_ROUNDS = 3
"""Rounds of 'drop the worst observation of each point, re-triangulate' for new multi-view tracks."""
FINAL_BA_ROUNDS = 2
"""Global BA, filter, and BA again if the filter removed anything."""


class ReprojectionSummary(NamedTuple):
    """Reprojection error of the model's observations in pixels."""

    rms_px: float
    mean_px: float
    median_px: float
    num_observations: int


@dataclass
class ReconstructionStats:
    """Numbers for report.json."""

    reprojection_before_ba: ReprojectionSummary
    reprojection_after_ba: ReprojectionSummary
    pair_inliers: dict[str, int]          # "a.png|b.png" -> RANSAC (F) inliers
    initial_pair: tuple[str, str]
    stage_seconds: dict[str, float]
    initial_pair_median_angle_deg: float
    bundle_adjustment_iterations: int


@dataclass
class InitialPairDiagnostics:
    """What the figures show about the initial pair (i, j)."""

    i: int
    j: int
    uv_i: np.ndarray               # (K, 2) all putative correspondences
    uv_j: np.ndarray               # (K, 2)
    inlier_mask: np.ndarray        # (K,) RANSAC (F) inliers
    points_linear: np.ndarray      # (L, 3) DLT points of the inliers in front of both cameras
    points_nonlinear: np.ndarray   # (L, 3) the same after non-linear triangulation
    pose_i: CameraPose             # the two cameras in the initial pair's frame (i at the origin)
    pose_j: CameraPose


@dataclass
class SparseModel:
    """Registered cameras and triangulated tracks with their observations."""

    image_names: list[str]
    poses: dict[int, CameraPose]           # registered image index -> world-to-camera pose
    unregistered: dict[int, str]           # image index -> why it could not be registered
    points: np.ndarray                     # (P, 3)
    point_colors: np.ndarray               # (P, 3) uint8
    point_track_ids: np.ndarray            # (P,) track of each point
    obs_camera: np.ndarray                 # (O,) image index
    obs_point: np.ndarray                  # (O,) index into points
    obs_uv: np.ndarray                     # (O, 2) pixels
    point_errors: np.ndarray               # (P,) mean reprojection error in pixels
    stats: ReconstructionStats
    initial_pair_diagnostics: InitialPairDiagnostics
    registration_order: list[int] = field(default_factory=list)
    cameras: list[Camera] = field(default_factory=list)   # image index -> intrinsics (refined by the BA)

    @property
    def visibility(self) -> np.ndarray:
        """(P, M) bool: point p is observed in image m."""
        visible = np.zeros((len(self.points), len(self.image_names)), bool)
        visible[self.obs_point, self.obs_camera] = True
        return visible


class PairGeometry(NamedTuple):
    """Correspondences of one image pair through shared tracks, and their robust fundamental matrix."""

    i: int
    j: int
    track_ids: np.ndarray
    uv_i: np.ndarray
    uv_j: np.ndarray
    fundamental: FundamentalResult


class InitialPairCandidate(NamedTuple):
    """A pair triangulated in its own frame (camera i at the origin, baseline 1)."""

    geometry: PairGeometry
    pose_j: CameraPose
    track_ids: np.ndarray          # (L,) inlier tracks in front of both cameras
    points_linear: np.ndarray      # (L, 3)
    points: np.ndarray             # (L, 3) non-linear
    well_conditioned: np.ndarray   # (L,) bool: error and angle within the filter limits
    median_angle_deg: float


# ----------------------------------------------------------------------------------------------------
# Pure helpers


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


def pose_arrays(poses: dict[int, CameraPose], num_images: int) -> tuple[np.ndarray, np.ndarray]:
    """R (M, 3, 3) and t (M, 3) indexed by image; NaN for images without a pose."""
    R, t = np.full((num_images, 3, 3), np.nan), np.full((num_images, 3), np.nan)
    for m, pose in poses.items():
        R[m], t[m] = pose.R, pose.t
    return R, t


def observations_of(tracks: Tracks, poses: dict[int, CameraPose], obs_ids: np.ndarray,
                    point_index: np.ndarray, num_points: int) -> Observations:
    """Flat Observations for the given track observations, with each observation's camera pose."""
    R, t = pose_arrays(poses, len(tracks.image_names))
    images = tracks.image_index[obs_ids]
    return Observations(R=R[images], t=t[images], uv=tracks.uv[obs_ids], point_index=point_index,
                        num_points=num_points)


def observation_errors(K: np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """||r_o|| in pixels, inf where the point is behind the observing camera or not finite."""
    x_cam_z = np.einsum("oj,oj->o", obs.R[:, 2], points[obs.point_index]) + obs.t[:, 2]
    error = np.linalg.norm(reprojection_residuals(K, obs, points), axis=1)
    return np.where((x_cam_z > 0) & np.isfinite(error), error, np.inf)


def summarize(errors: np.ndarray) -> ReprojectionSummary:
    if len(errors) == 0:
        return ReprojectionSummary(float("nan"), float("nan"), float("nan"), 0)
    return ReprojectionSummary(rms_px=float(np.sqrt(np.mean(errors**2))), mean_px=float(np.mean(errors)),
                               median_px=float(np.median(errors)), num_observations=len(errors))


def triangulate_robust(K: np.ndarray, obs: Observations, max_error_px: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view points; each round drops every point's worst observation above max_error_px (keeping 2+).

    Returns (points (P, 3), kept (O,) bool: observations within max_error_px of their point).
    """
    kept = np.ones(len(obs.uv), bool)
    points = np.zeros((obs.num_points, 3))
    for _ in range(ROBUST_TRIANGULATION_ROUNDS):
        subset = Observations(obs.R[kept], obs.t[kept], obs.uv[kept], obs.point_index[kept], obs.num_points)
        points = triangulate_nonlinear(K, subset, triangulate_linear(K, subset).points).points
        errors = observation_errors(K, obs, points)
        masked = np.where(kept, errors, -1.0)
        worst = np.full(obs.num_points, -1.0)
        np.maximum.at(worst, obs.point_index, masked)
        counts = np.bincount(obs.point_index[kept], minlength=obs.num_points)
        is_worst = masked == worst[obs.point_index]
        drop = kept & is_worst & (masked > max_error_px) & (counts[obs.point_index] > 2)
        if not drop.any():
            break
        kept &= ~drop
    errors = observation_errors(K, obs, points)
    return points, kept & (errors <= max_error_px)


def evaluate_initial_pair(K: np.ndarray, geometry: PairGeometry, config: ReconstructionConfig
                          ) -> InitialPairCandidate:
    """E = K^T F K, chirality, DLT + non-linear triangulation of the F inliers, and their parallax."""
    inliers = geometry.fundamental.inlier_mask
    uv_i, uv_j = geometry.uv_i[inliers], geometry.uv_j[inliers]
    relative = choose_relative_pose(essential_from_fundamental(geometry.fundamental.F, K), K, uv_i, uv_j)
    front = relative.in_front
    pose_j = relative.pose
    obs = observations_for_pair(np.eye(3), np.zeros(3), pose_j.R, pose_j.t, uv_i[front], uv_j[front])
    points = triangulate_nonlinear(K, obs, relative.points[front]).points
    errors = observation_errors(K, obs, points).reshape(2, -1).max(axis=0)
    centers = np.concatenate([np.zeros((front.sum(), 3)), np.broadcast_to(pose_j.center, (front.sum(), 3))])
    angles = triangulation_angle_deg(centers, obs.point_index, points)
    well_conditioned = (errors <= config.filter.max_reprojection_px) & (
        angles >= config.filter.min_triangulation_angle_deg)
    return InitialPairCandidate(
        geometry=geometry, pose_j=pose_j, track_ids=geometry.track_ids[inliers][front],
        points_linear=relative.points[front], points=points, well_conditioned=well_conditioned,
        median_angle_deg=float(np.median(angles)) if len(angles) else 0.0,
    )


# ----------------------------------------------------------------------------------------------------
# Orchestration


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


class _Model:
    """Mutable reconstruction state, indexed by track and by flat observation.

    The geometry (F, E, PnP, triangulation) works with the pinhole K of the initial camera on
    `tracks.uv` = the measured pixels `observed_uv` transferred through each image's current camera
    (distortion and refined focal included) to that K; errors and the BA use the measured pixels.
    """

    def __init__(self, tracks: Tracks, cameras: list[Camera], refine: IntrinsicsRefinement) -> None:
        self.tracks, self.K, self.refine = tracks, cameras[0].pinhole().K, refine
        self.observed_uv = tracks.uv
        self.use_cameras(cameras)
        self.poses: dict[int, CameraPose] = {}
        self.order: list[int] = []
        self.point_xyz = np.zeros((tracks.num_tracks, 3))
        self.has_point = np.zeros(tracks.num_tracks, bool)
        self.obs_used = np.zeros(len(tracks.track_index), bool)

    def used_observations(self) -> np.ndarray:
        return np.flatnonzero(self.obs_used)

    def use_cameras(self, cameras: list[Camera]) -> None:
        """Adopt new intrinsics per image: the working pixels follow them."""
        self.cameras = cameras
        source = Camera.take(cameras, self.tracks.image_index)
        working = transfer_pixels(source, Camera.from_K(self.K), self.observed_uv)
        self.tracks = replace(self.tracks, uv=working)

    def errors_of(self, obs_ids: np.ndarray) -> np.ndarray:
        obs = observations_of(self.tracks, self.poses, obs_ids, self.tracks.track_index[obs_ids],
                              self.tracks.num_tracks)._replace(uv=self.observed_uv[obs_ids])
        camera = Camera.take(self.cameras, self.tracks.image_index[obs_ids])
        return observation_errors(camera, obs, self.point_xyz)

    def readmit(self, max_error_px: float) -> None:
        """Take back the observations of registered images and triangulated tracks within max_error_px:
        those an earlier filter dropped while the intrinsics were still wrong."""
        tracks = self.tracks
        candidates = np.flatnonzero(~self.obs_used & self.has_point[tracks.track_index]
                                    & np.isin(tracks.image_index, self.order))
        self.obs_used[candidates[self.errors_of(candidates) <= max_error_px]] = True

    def filter(self, max_error_px: float, min_angle_deg: float) -> None:
        """Drop observations above max_error_px (or behind the camera), then points with < 2
        observations or a triangulation angle below min_angle_deg."""
        used = self.used_observations()
        self.obs_used[used[self.errors_of(used) > max_error_px]] = False
        used = self.used_observations()
        track = self.tracks.track_index[used]
        counts = np.bincount(track, minlength=self.tracks.num_tracks)
        R, t = pose_arrays(self.poses, len(self.tracks.image_names))
        centers = -np.einsum("mji,mj->mi", R, t)[self.tracks.image_index[used]]
        angles = triangulation_angle_deg(centers, track, self.point_xyz)
        drop = self.has_point & ((counts < 2) | (angles < min_angle_deg))
        self.has_point[drop] = False
        self.obs_used[drop[self.tracks.track_index]] = False

    def bundle_adjust(self, config: ReconstructionConfig, window: list[int] | None
                      ) -> tuple[float, float, int]:
        """Global BA (window None: first camera fixed, scale by the second) or local BA over `window`;
        both refine the intrinsics as `self.refine` says (as COLMAP's local BA does), and the model
        adopts them."""
        from estimation.bundle_adjustment.factor_graph import bundle_adjust

        used = self.used_observations()
        if window is not None:
            in_window = np.isin(self.tracks.image_index[used], window)
            used = used[np.isin(self.tracks.track_index[used], self.tracks.track_index[used][in_window])]
        cameras = list(self.order)
        camera_position = {m: k for k, m in enumerate(cameras)}
        track_ids, point_index = np.unique(self.tracks.track_index[used], return_inverse=True)
        outside = [camera_position[m] for m in cameras if window is not None and m not in window]
        fixed, scale_reference = (outside, None) if len(outside) >= 2 else ([0], 1)
        ba_config = config.bundle_adjustment
        if window is not None:
            ba_config = ba_config.model_copy(update={"max_iterations": ba_config.local_max_iterations})
        result = bundle_adjust(
            [self.cameras[m] for m in cameras], [self.poses[m] for m in cameras], self.point_xyz[track_ids],
            np.array([camera_position[int(m)] for m in self.tracks.image_index[used]], dtype=np.int64),
            point_index, self.observed_uv[used], ba_config,
            fixed_cameras=fixed, scale_reference=scale_reference,
            refine=self.refine,
        )
        for m, pose in zip(cameras, result.poses, strict=True):
            self.poses[m] = pose
        self.point_xyz[track_ids] = result.points
        if self.refine.refines(self.cameras[0].model):
            refined = dict(zip(cameras, result.cameras, strict=True))
            shared = None if self.refine.per_image else result.cameras[0]
            self.use_cameras([refined.get(m, shared or camera) for m, camera in enumerate(self.cameras)])
        return result.initial_rms_px, result.final_rms_px, result.iterations


def _pair_geometries(tracks: Tracks, config: ReconstructionConfig, progress: ProgressCallback | None,
                     fraction: tuple[float, float]) -> list[PairGeometry]:
    pairs = [(i, j) for i, j, n in co_visible_pairs(tracks) if n >= MIN_F_CORRESPONDENCES]
    geometries = []
    for done, (i, j) in enumerate(pairs):
        if progress:
            progress(f"pair geometry {pair_name(tracks, i, j)}",
                     fraction[0] + (fraction[1] - fraction[0]) * done / len(pairs))
        track_ids, uv_i, uv_j = tracks.pair_correspondences(i, j)
        try:
            fundamental = ransac_fundamental(uv_i, uv_j, config.ransac)
        except DegenerateConfigurationError:
            continue
        geometries.append(PairGeometry(i, j, track_ids, uv_i, uv_j, fundamental))
    return geometries


def _select_initial_pair(K: np.ndarray, tracks: Tracks, geometries: list[PairGeometry],
                         config: ReconstructionConfig) -> InitialPairCandidate:
    """Among the pairs with most F inliers, the one with most well-conditioned points (then the widest
    median triangulation angle) whose median angle reaches min_initial_pair_median_angle_deg."""
    ranked = sorted(geometries, key=lambda g: -int(g.fundamental.inlier_mask.sum()))
    enough = [g for g in ranked if g.fundamental.inlier_mask.sum() >= config.min_initial_pair_inliers]
    if not enough:
        best = "no pair shares 8+ tracks, so 0"
        if ranked:
            best = (f"the best pair {pair_name(tracks, ranked[0].i, ranked[0].j)} has "
                    f"{int(ranked[0].fundamental.inlier_mask.sum())}")
        raise DegenerateConfigurationError(
            f"too few matches for an initial pair: {best} RANSAC inliers, need "
            f"{config.min_initial_pair_inliers} (min_initial_pair_inliers)"
        )
    candidates = [evaluate_initial_pair(K, g, config) for g in enough[: config.initial_pair_candidates]]
    with_parallax = [c for c in candidates if c.median_angle_deg >= config.min_initial_pair_median_angle_deg
                     and c.well_conditioned.sum() >= config.min_initial_pair_inliers]
    if not with_parallax:
        best = max(candidates, key=lambda c: c.median_angle_deg)
        raise DegenerateConfigurationError(
            "degenerate initial pair (pure rotation or too little parallax): the largest median "
            f"triangulation angle, {best.median_angle_deg:.2f} deg for "
            f"{pair_name(tracks, best.geometry.i, best.geometry.j)}, is below "
            f"{config.min_initial_pair_median_angle_deg} deg, or too few points are well conditioned"
        )
    return max(with_parallax, key=lambda c: (int(c.well_conditioned.sum()), c.median_angle_deg))


def _register(model: _Model, image: int, config: ReconstructionConfig) -> str | None:
    """PnP RANSAC + non-linear PnP for `image`; adds its 2D-3D inliers. Returns a failure reason or None."""
    tracks = model.tracks
    obs_ids = np.flatnonzero((tracks.image_index == image) & model.has_point[tracks.track_index])
    if len(obs_ids) < config.min_pnp_correspondences:
        return (f"only {len(obs_ids)} 2D-3D correspondences with the reconstructed points "
                f"(need {config.min_pnp_correspondences})")
    points, uv = model.point_xyz[tracks.track_index[obs_ids]], tracks.uv[obs_ids]
    try:
        ransac = pnp_ransac(model.K, points, uv, config.ransac)
    except DegenerateConfigurationError as error:
        return str(error)
    if ransac.inlier_mask.sum() < config.min_pnp_inliers:
        return (f"PnP RANSAC found only {int(ransac.inlier_mask.sum())} inliers among {len(obs_ids)} "
                f"2D-3D correspondences (need {config.min_pnp_inliers})")
    pose = pnp_nonlinear(model.K, points[ransac.inlier_mask], uv[ransac.inlier_mask], ransac.pose).pose
    errors = reprojection_errors(model.K, pose.R, pose.t, points, uv)
    model.poses[image] = pose
    model.order.append(image)
    model.obs_used[obs_ids[errors < config.ransac.pnp_threshold_px]] = True
    return None


def _triangulate_new_tracks(model: _Model, image: int, config: ReconstructionConfig) -> None:
    """Tracks seen by `image` and another registered image that have no point yet."""
    tracks = model.tracks
    registered = np.isin(tracks.image_index, model.order)
    in_image = np.zeros(tracks.num_tracks, bool)
    in_image[tracks.track_index[tracks.image_index == image]] = True
    registered_counts = np.bincount(tracks.track_index[registered], minlength=tracks.num_tracks)
    new = in_image & ~model.has_point & (registered_counts >= 2)
    obs_ids = np.flatnonzero(registered & new[tracks.track_index])
    if len(obs_ids) == 0:
        return
    track_ids, point_index = np.unique(tracks.track_index[obs_ids], return_inverse=True)
    obs = observations_of(tracks, model.poses, obs_ids, point_index, len(track_ids))
    points, kept = triangulate_robust(model.K, obs, config.filter.max_reprojection_px)
    good = np.bincount(point_index[kept], minlength=len(track_ids)) >= 2
    model.point_xyz[track_ids[good]] = points[good]
    model.has_point[track_ids[good]] = True
    model.obs_used[obs_ids[kept & good[point_index]]] = True


def _initialize(model: _Model, candidate: InitialPairCandidate) -> None:
    g = candidate.geometry
    model.poses[g.i] = CameraPose(R=np.eye(3), t=np.zeros(3))
    model.poses[g.j] = candidate.pose_j
    model.order.extend([g.i, g.j])
    keep = candidate.well_conditioned
    model.point_xyz[candidate.track_ids[keep]] = candidate.points[keep]
    model.has_point[candidate.track_ids[keep]] = True
    tracks = model.tracks
    model.obs_used[np.isin(tracks.image_index, [g.i, g.j]) & model.has_point[tracks.track_index]] = True


def _to_sparse_model(model: _Model, unregistered: dict[int, str], stats: ReconstructionStats,
                     diagnostics: InitialPairDiagnostics) -> SparseModel:
    tracks = model.tracks
    used = model.used_observations()
    track_ids, obs_point = np.unique(tracks.track_index[used], return_inverse=True)
    errors = model.errors_of(used)
    point_errors = np.bincount(obs_point, weights=errors, minlength=len(track_ids)) / np.maximum(
        np.bincount(obs_point, minlength=len(track_ids)), 1)
    return SparseModel(
        image_names=list(tracks.image_names), poses={m: model.poses[m] for m in model.order},
        unregistered=unregistered, points=model.point_xyz[track_ids].copy(),
        point_colors=tracks.colors[track_ids], point_track_ids=track_ids,
        obs_camera=tracks.image_index[used].copy(), obs_point=obs_point,
        obs_uv=model.observed_uv[used].copy(),
        point_errors=point_errors, stats=stats, initial_pair_diagnostics=diagnostics,
        registration_order=list(model.order), cameras=list(model.cameras),
    )


def run_incremental(tracks: Tracks, K: CameraInput, config: ReconstructionConfig,
                    progress: ProgressCallback | None = None,
                    refine: IntrinsicsRefinement = IntrinsicsRefinement()) -> SparseModel:
    """Incremental SfM: initial pair by inliers and parallax, then PnP registration by most 2D-3D matches.

    The geometry works in the pixel coordinates of `tracks`; `K` (a 3x3 K or a Camera shared by every
    image, or a list of Cameras, one per image) holds the initial intrinsics; every bundle adjustment
    refines them as `refine` says, the final rounds take back observations dropped under the earlier
    intrinsics, and the model's `cameras` carry the result.
    Raises DegenerateConfigurationError if no pair can start.
    """
    num_images = len(tracks.image_names)
    if num_images < 2:
        raise InputError(f"Structure from Motion needs at least 2 images, got {num_images}")
    timer = _Timer()
    cameras = [as_camera(K)] * num_images if is_shared(K) else [as_camera(camera) for camera in K]
    if len(cameras) != num_images:
        raise InputError(f"got {len(cameras)} cameras for {num_images} images (need one per image)")
    model = _Model(tracks, cameras, refine)
    filter_limits = (config.filter.max_reprojection_px, config.filter.min_triangulation_angle_deg)

    with timer.stage("pair geometry"):
        geometries = _pair_geometries(tracks, config, progress, (0.0, 0.2))
    pair_inliers = {pair_name(tracks, g.i, g.j): int(g.fundamental.inlier_mask.sum()) for g in geometries}

    if progress:
        progress("initial pair", 0.2)
    with timer.stage("initial pair"):
        initial = _select_initial_pair(model.K, tracks, geometries, config)
        _initialize(model, initial)
        model.filter(*filter_limits)
    g = initial.geometry
    diagnostics = InitialPairDiagnostics(
        i=g.i, j=g.j, uv_i=g.uv_i, uv_j=g.uv_j, inlier_mask=g.fundamental.inlier_mask,
        points_linear=initial.points_linear, points_nonlinear=initial.points,
        pose_i=CameraPose(R=np.eye(3), t=np.zeros(3)), pose_j=initial.pose_j,
    )

    failures: dict[int, str] = {}
    while True:
        waiting = [m for m in range(num_images) if m not in model.poses and m not in failures]
        if not waiting:
            break
        obs_with_point = model.has_point[tracks.track_index]
        counts = np.bincount(tracks.image_index[obs_with_point], minlength=num_images)
        image = max(waiting, key=lambda m: counts[m])
        if progress:
            progress(f"register {tracks.image_names[image]}", 0.25 + 0.65 * len(model.order) / num_images)
        with timer.stage("registration"):
            reason = _register(model, image, config)
        if reason is not None:
            failures[image] = reason
            continue
        failures.clear()  # new points may let earlier failures register now
        with timer.stage("triangulation"):
            _triangulate_new_tracks(model, image, config)
            model.filter(*filter_limits)
        with timer.stage("local bundle adjustment"):
            model.bundle_adjust(config, window=model.order[-config.bundle_adjustment.local_window:])
            model.filter(*filter_limits)

    if progress:
        progress("bundle adjustment", 0.9)
    before = summarize(model.errors_of(model.used_observations()))
    iterations = 0
    with timer.stage("bundle adjustment"):
        for _ in range(FINAL_BA_ROUNDS):
            iterations += model.bundle_adjust(config, window=None)[2]
            num_used = model.obs_used.sum()
            if refine.refines(model.cameras[0].model):
                model.readmit(config.filter.max_reprojection_px)
            model.filter(*filter_limits)
            if model.obs_used.sum() == num_used:
                break
    after = summarize(model.errors_of(model.used_observations()))
    if progress:
        progress("done", 1.0)

    stats = ReconstructionStats(
        reprojection_before_ba=before, reprojection_after_ba=after, pair_inliers=pair_inliers,
        initial_pair=(tracks.image_names[g.i], tracks.image_names[g.j]), stage_seconds=timer.seconds,
        initial_pair_median_angle_deg=initial.median_angle_deg, bundle_adjustment_iterations=iterations,
    )
    return _to_sparse_model(model, failures, stats, diagnostics)
