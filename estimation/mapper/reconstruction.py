"""The reconstruction being built: registered images, 3D points and the observations that support them.

A `Reconstruction` sits on the feature `Tracks` (the correspondence graph the matcher produced: a track is a
set of keypoint observations linked by matches, at most one per image). A 3D point owns a subset of one
track's observations; each observation belongs to at most one point (`obs_point`, -1 when it supports none).
One track may be split into several points (observations that disagree), which `merge_tracks` joins again
when one point explains them all, and `complete_tracks` continues a point into newly registered images, as
COLMAP's IncrementalTriangulator does with its correspondence graph. Everything is vectorized over flat
observation arrays; the named methods are the only way the mapper changes the reconstruction.

Intrinsics: every image has a `Camera` (distortion included), refined by the global BA. The minimal
solvers and triangulation work with the pinhole `K` of the first camera on `tracks.uv`, the measured
pixels `observed_uv` transferred through each image's current camera to K; reprojection errors, the
filters and the BA use the measured pixels and the cameras.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from estimation.config import BundleAdjustmentConfig
from estimation.geometry.alignment import Similarity
from estimation.geometry.projection import (
    Camera,
    CameraInput,
    as_camera,
    is_shared,
    observation_cameras,
    reprojection_errors,
    transfer_pixels,
)
from estimation.geometry.triangulation import (
    Observations,
    triangulate_nonlinear,
    triangulate_ransac,
    triangulation_angle_reaches,
)
from estimation.types import CameraPose, Tracks

if TYPE_CHECKING:  # GTSAM loads only when a bundle adjustment runs
    from estimation.bundle_adjustment.factor_graph import BundleAdjustmentResult, IntrinsicsRefinement

TWO_VIEW_ERROR_FACTOR = 0.5
"""A two-view point is fitted to both rays, so each of its reprojection errors is about half the pair's
epipolar distance: half the limit keeps two-view points as consistent as the pair's verification (and
drops the wrong matches lying up to twice that far from the epipolar line, which nothing else can
reveal; measured on synthetic rings, they were the largest error left)."""
MAX_MERGE_ROUNDS = 3
"""merge_tracks joins two points of a track per round; tracks split three ways or more need more rounds."""


def pixel_noise_sigma(errors: np.ndarray, variance_factors: np.ndarray) -> float:
    """Per-axis pixel noise sigma = median_o(e_o / sqrt(f_o)) / sqrt(2 ln 2), where E[e_o^2] = 2 sigma^2 f_o.

    For an observation of a point fitted to L observations (2L measurements, 3 unknowns, mean leverage
    h = 3 / (2L)), f = 1 - h when the observation is part of the fit and 1 + h when it is not. So
    corrected, e_o is about Rayleigh(sigma), whose median is sigma sqrt(2 ln 2); the median ignores the
    outliers (up to half). errors (O,) pixel norms, variance_factors (O,) f_o. NaN without observations.
    """
    if len(errors) == 0:
        return float("nan")
    corrected = np.asarray(errors, float) / np.sqrt(np.asarray(variance_factors, float))
    return float(np.median(corrected) / np.sqrt(2.0 * np.log(2.0)))


class Reconstruction:
    """Registered images (world-to-camera poses) and points over the observations of `tracks`."""

    def __init__(self, tracks: Tracks, camera: CameraInput,
                 refine: IntrinsicsRefinement | None = None) -> None:
        num_images = len(tracks.image_names)
        cameras = [as_camera(camera)] * num_images if is_shared(camera) else list(camera)
        self.K = cameras[0].pinhole().K
        self.refine = refine
        self.observed_uv = tracks.uv
        self.tracks = tracks
        self.use_cameras(cameras)
        self.R = np.full((num_images, 3, 3), np.nan)
        self.t = np.full((num_images, 3), np.nan)
        self.registered = np.zeros(num_images, bool)
        self.order: list[int] = []
        self.obs_point = np.full(len(tracks.track_index), -1, np.int64)
        self.point_xyz = np.zeros((0, 3))
        self.point_track = np.zeros(0, np.int64)
        self.point_alive = np.zeros(0, bool)

    # ------------------------------------------------------------------------------------------ images

    def use_cameras(self, cameras: list[Camera]) -> None:
        """Adopt new intrinsics per image: the working pixels follow them."""
        self.cameras = cameras
        source = observation_cameras(cameras, self.tracks.image_index)
        working = transfer_pixels(source, Camera.from_K(self.K), self.observed_uv)
        self.tracks = replace(self.tracks, uv=working)

    def pose(self, image: int) -> CameraPose:
        return CameraPose(R=self.R[image].copy(), t=self.t[image].copy())

    def _poses_of(self, images: list[int]) -> list[CameraPose]:
        """The images' poses as views of one copy of their rows (two gathers instead of a copy per array)."""
        rotations, translations = self.R.take(images, axis=0), self.t.take(images, axis=0)
        return [CameraPose(R, t) for R, t in zip(rotations, translations, strict=True)]

    @property
    def poses(self) -> dict[int, CameraPose]:
        """Registered image -> pose, in registration order."""
        return dict(zip(self.order, self._poses_of(self.order), strict=True))

    def register_image(self, image: int, pose: CameraPose) -> None:
        if self.registered[image]:
            raise ValueError(f"image {image} is already registered")
        self.set_pose(image, pose)
        self.registered[image] = True
        self.order.append(image)

    def set_pose(self, image: int, pose: CameraPose) -> None:
        self.R[image], self.t[image] = pose.R, pose.t

    def deregister_image(self, image: int) -> None:
        """Forget the image's pose and every observation it contributes (points left with < 2 vanish)."""
        in_image = np.flatnonzero((self.tracks.image_index == image) & (self.obs_point >= 0))
        self.remove_observations(in_image)
        self.registered[image] = False
        self.R[image], self.t[image] = np.nan, np.nan
        self.order.remove(image)

    def absorb(self, other: Reconstruction, similarity: Similarity) -> list[int]:
        """Register the images of `other` (a model of the same tracks over other images) with their poses
        moved by X' = s R X + t, and add its points on the tracks this one has no point of, moved alike
        (the shared tracks keep this model's point; completion adds the other's observations to it).
        Returns the images added, in the other's registration order."""
        added = [image for image in other.order if not self.registered[image]]
        for image in added:
            self.register_image(image, similarity.apply_pose(other.pose(image)))
        used = other.used_observations()
        used = used[self.registered[self.tracks.image_index[used]] & np.isin(
            self.tracks.image_index[used], added)]
        fresh = ~self._track_has_point()[self.tracks.track_index[used]]
        used = used[fresh]
        points, new_point_of_obs = np.unique(other.obs_point[used], return_inverse=True)
        keep = np.bincount(new_point_of_obs, minlength=len(points)) >= 2
        position = np.cumsum(keep) - 1
        in_kept = keep[new_point_of_obs]
        self.add_points(similarity.apply_points(other.point_xyz[points[keep]]), used[in_kept],
                        position[new_point_of_obs[in_kept]])
        return added

    # ------------------------------------------------------------------------------------------ points

    @property
    def num_points(self) -> int:
        return int(self.point_alive.sum())

    def used_observations(self) -> np.ndarray:
        return np.flatnonzero(self.obs_point >= 0)

    def point_observation_counts(self) -> np.ndarray:
        # Free observations (-1) fall in bin 0 and are dropped: no mask and copy of the used ones.
        return np.bincount(self.obs_point + 1, minlength=len(self.point_alive) + 1)[1:]

    def points_seen_in(self, images: np.ndarray | list[int]) -> np.ndarray:
        """(points,) bool: the points with an observation in one of `images` (a mask: no np.unique)."""
        used = self.used_observations()
        in_images = np.zeros(len(self.registered), bool)
        in_images[np.asarray(images, np.int64)] = True
        seen = np.zeros(len(self.point_alive), bool)
        seen[self.obs_point[used[in_images[self.tracks.image_index[used]]]]] = True
        return seen

    def add_points(self, xyz: np.ndarray, obs_ids: np.ndarray, new_point_of_obs: np.ndarray) -> np.ndarray:
        """New points xyz (n, 3), observation obs_ids[k] supporting point new_point_of_obs[k] in [0, n).

        Each observation must be free, in a registered image, and of the same track as its point's others.
        Returns the new point ids.
        """
        obs_ids = np.asarray(obs_ids, np.int64)
        self._check_free(obs_ids)
        first = len(self.point_alive)
        ids = first + np.arange(len(xyz))
        track_of_point = np.full(len(xyz), -1, np.int64)
        track_of_point[new_point_of_obs] = self.tracks.track_index[obs_ids]
        if np.any(track_of_point[new_point_of_obs] != self.tracks.track_index[obs_ids]):
            raise ValueError("a point's observations must all belong to one track")
        self.point_xyz = np.concatenate([self.point_xyz, np.asarray(xyz, float).reshape(-1, 3)])
        self.point_track = np.concatenate([self.point_track, track_of_point])
        self.point_alive = np.concatenate([self.point_alive, np.ones(len(xyz), bool)])
        self.obs_point[obs_ids] = ids[new_point_of_obs]
        return ids

    def add_observations(self, obs_ids: np.ndarray, point_ids: np.ndarray) -> None:
        """Observation obs_ids[k] now supports the live point point_ids[k] (same track; free, registered)."""
        obs_ids, point_ids = np.asarray(obs_ids, np.int64), np.asarray(point_ids, np.int64)
        self._check_free(obs_ids)
        if np.any(self.point_track[point_ids] != self.tracks.track_index[obs_ids]) or not np.all(
            self.point_alive[point_ids]
        ):
            raise ValueError("an observation can only join a live point of its own track")
        self.obs_point[obs_ids] = point_ids

    def remove_observations(self, obs_ids: np.ndarray) -> None:
        """The observations support no point any more; points left with fewer than two are deleted."""
        obs_ids = np.asarray(obs_ids, np.int64)
        touched = np.unique(self.obs_point[obs_ids])
        self.obs_point[obs_ids] = -1
        touched = touched[touched >= 0]
        self.delete_points(touched[self.point_observation_counts()[touched] < 2])

    def delete_points(self, point_ids: np.ndarray) -> None:
        point_ids = np.asarray(point_ids, np.int64)
        if len(point_ids) == 0:
            return
        self.point_alive[point_ids] = False
        doomed = np.zeros(len(self.point_alive), bool)
        doomed[point_ids] = True
        self.obs_point[(self.obs_point >= 0) & doomed[np.maximum(self.obs_point, 0)]] = -1

    def _check_free(self, obs_ids: np.ndarray) -> None:
        if np.any(self.obs_point[obs_ids] >= 0):
            raise ValueError("an observation already supports a point")
        if not np.all(self.registered[self.tracks.image_index[obs_ids]]):
            raise ValueError("only observations in registered images can support a point")

    # ------------------------------------------------------------------------------------------ geometry

    def observations(self, obs_ids: np.ndarray, point_index: np.ndarray, num_points: int) -> Observations:
        """Flat Observations of the given track observations with their image's pose."""
        images = self.tracks.image_index[obs_ids]
        return Observations(
            R=self.R.take(images, axis=0),      # take: numpy 2's fancy row indexing costs several times more
            t=self.t.take(images, axis=0),
            uv=self.tracks.uv.take(obs_ids, axis=0),
            point_index=point_index,
            num_points=num_points,
        )

    def errors(self, obs_ids: np.ndarray, point_ids: np.ndarray | None = None) -> np.ndarray:
        """Reprojection error (measured px through the image's camera, inf behind it) of each observation
        against its point, or against point_ids[k] when given."""
        obs_ids = np.asarray(obs_ids, np.int64)
        points = self.obs_point[obs_ids] if point_ids is None else np.asarray(point_ids, np.int64)
        images = self.tracks.image_index[obs_ids]
        obs = Observations(R=self.R.take(images, axis=0), t=self.t.take(images, axis=0),
                           uv=self.observed_uv.take(obs_ids, axis=0), point_index=points,
                           num_points=len(self.point_alive))
        camera = observation_cameras(self.cameras, images)
        return reprojection_errors(camera, obs, self.point_xyz)

    def noise_sigma(self, max_error_px: float) -> float:
        """Per-axis pixel noise (`pixel_noise_sigma`) of the observations within max_error_px of their
        point: those supporting one, and the free ones of their tracks in registered images (against the
        closest point of the track). Measured on this fixed set, it does not shrink with a tighter filter."""
        used = self.used_observations()
        counts = self.point_observation_counts()
        free, free_point, free_errors = self._closest_points(self._free_candidates())
        errors = np.concatenate([self.errors(used), free_errors])
        leverage = 1.5 / counts[np.concatenate([self.obs_point[used], free_point])]
        factors = np.concatenate([1.0 - leverage[: len(used)], 1.0 + leverage[len(used):]])
        within = errors < max_error_px
        return pixel_noise_sigma(errors[within], factors[within])

    def seen_wide(self, point_ids: np.ndarray, min_angle_deg: float) -> np.ndarray:
        """Whether two viewing rays of each given live point (point_ids sorted, unique) are min_angle_deg
        or more apart (`triangulation_angle_reaches`)."""
        point_ids = np.asarray(point_ids, np.int64)
        position = np.full(len(self.point_alive), -1, np.int64)       # point -> its index in point_ids
        position[point_ids] = np.arange(len(point_ids))
        used = self.used_observations()
        compact = position[self.obs_point[used]]
        used, compact = used[compact >= 0], compact[compact >= 0]
        centers = -np.einsum("mji,mj->mi", self.R, self.t)        # per image: C = -R^T t
        return triangulation_angle_reaches(centers.take(self.tracks.image_index[used], axis=0), compact,
                                           self.point_xyz.take(point_ids, axis=0), min_angle_deg)

    def visible_uv(self, image: int) -> np.ndarray:
        """Pixels of the image's observations whose track has a live point (its 2D-3D candidates)."""
        in_image = np.flatnonzero(self.tracks.image_index == image)
        return self.tracks.uv[in_image[self._track_has_point()[self.tracks.track_index[in_image]]]]

    def correspondences_2d3d(self, image: int) -> tuple[np.ndarray, np.ndarray]:
        """(observation ids, point ids) of the image's observations whose track has a live point (for a
        split track, its point with most observations)."""
        in_image = np.flatnonzero(self.tracks.image_index == image)
        point_of_track = self.main_point_of_track()
        points = point_of_track[self.tracks.track_index[in_image]]
        return in_image[points >= 0], points[points >= 0]

    def _live_points(self, point_ids: np.ndarray | None = None) -> np.ndarray:
        """(points,) bool: the live points, only those among point_ids when given (a mask: cheaper than
        set operations on the ids)."""
        if point_ids is None:
            return self.point_alive.copy()
        selected = np.zeros(len(self.point_alive), bool)
        selected[np.asarray(point_ids, np.int64)] = True
        return selected & self.point_alive

    def _track_has_point(self) -> np.ndarray:
        has = np.zeros(self.tracks.num_tracks, bool)
        has[self.point_track[self.point_alive]] = True
        return has

    def _ranked_points(self) -> np.ndarray:
        """The live points by track, within a track most observations first (ties: lower id): one stable
        sort of the key track (most + 1) + (most - count) (two-key np.lexsort cost twice as much)."""
        alive = np.flatnonzero(self.point_alive)
        counts = self.point_observation_counts()[alive]
        most = int(counts.max(initial=0))
        return alive[np.argsort(self.point_track[alive] * (most + 1) + (most - counts), kind="stable")]

    def main_point_of_track(self) -> np.ndarray:
        """Track -> its live point with most observations, -1 for none."""
        ranked = self._ranked_points()
        point_of_track = np.full(self.tracks.num_tracks, -1, np.int64)
        point_of_track[self.point_track[ranked[::-1]]] = ranked[::-1]  # the first of each track wins
        return point_of_track

    # ------------------------------------------------------------------------------------------ tracks

    def triangulate_tracks(
        self,
        track_ids: np.ndarray,
        max_error_px: float,
        min_angle_deg: float,
        hypotheses_per_point: int,
    ) -> int:
        """New points for the given tracks that have none yet, from their free observations in registered
        images (robust two-view hypotheses, `triangulate_ransac`). Returns the number of points added."""
        candidate = np.zeros(self.tracks.num_tracks, bool)
        candidate[np.asarray(track_ids, np.int64)] = True
        candidate &= ~self._track_has_point()
        obs_ids = np.flatnonzero(
            candidate[self.tracks.track_index]
            & (self.obs_point < 0)
            & self.registered[self.tracks.image_index]
        )
        per_track = np.bincount(self.tracks.track_index[obs_ids], minlength=self.tracks.num_tracks)
        enough = per_track >= 2
        obs_ids = obs_ids[enough[self.tracks.track_index[obs_ids]]]
        if len(obs_ids) == 0:
            return 0
        # Point k is the k-th track with enough observations (in track order).
        point_index = (np.cumsum(enough) - 1)[self.tracks.track_index[obs_ids]]
        result = triangulate_ransac(
            self.K,
            self.observations(obs_ids, point_index, int(enough.sum())),
            max_error_px,
            min_angle_deg,
            hypotheses_per_point,
        )
        keep = result.inlier_mask
        new_index = np.cumsum(result.valid) - 1
        self.add_points(result.points[result.valid], obs_ids[keep], new_index[point_index[keep]])
        return int(result.valid.sum())

    def complete_tracks(self, max_error_px: float, point_ids: np.ndarray | None = None) -> int:
        """Continue points into the free observations of their tracks in registered images that reproject
        within max_error_px (to the closest point of the track). Returns the observations added."""
        obs, points, errors = self._closest_points(self._free_candidates(), point_ids)
        accept = errors < max_error_px
        self.add_observations(obs[accept], points[accept])
        return int(accept.sum())

    def _free_candidates(self) -> np.ndarray:
        """Free observations in registered images."""
        return np.flatnonzero((self.obs_point < 0) & self.registered[self.tracks.image_index])

    def _closest_points(
        self, obs_ids: np.ndarray, point_ids: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(observations, point, error): each observation of obs_ids whose track has a live point (among
        point_ids when given) with the point of its track it reprojects closest to."""
        alive = np.flatnonzero(self._live_points(point_ids))
        alive = alive[np.argsort(self.point_track[alive], kind="stable")]       # by track
        per_track = np.bincount(self.point_track[alive], minlength=self.tracks.num_tracks)
        obs_ids = obs_ids[per_track[self.tracks.track_index[obs_ids]] > 0]
        if len(obs_ids) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        track_of_obs = self.tracks.track_index[obs_ids]
        begin = (np.cumsum(per_track) - per_track)[track_of_obs]               # its track's first in alive
        num_candidates = per_track[track_of_obs]
        # One (observation, point) candidate per point of the observation's track.
        cand_obs = np.repeat(obs_ids, num_candidates)
        offsets = np.arange(num_candidates.sum()) - np.repeat(
            np.cumsum(num_candidates) - num_candidates, num_candidates
        )
        cand_point = alive[np.repeat(begin, num_candidates) + offsets]
        errors = self.errors(cand_obs, cand_point)
        order = np.lexsort((errors, cand_obs))
        best = order[np.concatenate([[True], cand_obs[order][1:] != cand_obs[order][:-1]])]
        return cand_obs[best], cand_point[best], errors[best]

    def merge_tracks(self, max_error_px: float) -> int:
        """Join two points of one track when a single point, re-triangulated from both, explains every
        observation of both within max_error_px. Returns the number of merges."""
        merged = 0
        for _ in range(MAX_MERGE_ROUNDS):
            ranked = self._ranked_points()
            same_track = self.point_track[ranked[1:]] == self.point_track[ranked[:-1]]
            starts = np.concatenate([[True], ~same_track])  # first (largest) point of each track
            keep_ids = ranked[:-1][same_track & starts[:-1]]
            drop_ids = ranked[1:][same_track & starts[:-1]]
            if len(keep_ids) == 0:
                break
            used = self.used_observations()
            target = np.full(len(self.point_alive), -1, np.int64)
            target[keep_ids], target[drop_ids] = np.arange(len(keep_ids)), np.arange(len(keep_ids))
            involved = used[target[self.obs_point[used]] >= 0]
            pair_index = target[self.obs_point[involved]]
            obs = self.observations(involved, pair_index, len(keep_ids))
            points = triangulate_nonlinear(self.K, obs, self.point_xyz[keep_ids]).points
            worst = np.zeros(len(keep_ids))
            np.maximum.at(worst, pair_index, reprojection_errors(self.K, obs, points))
            ok = worst < max_error_px
            if not ok.any():
                break
            self.point_xyz[keep_ids[ok]] = points[ok]
            moving = involved[np.isin(self.obs_point[involved], drop_ids[ok])]
            self.obs_point[moving] = keep_ids[target[self.obs_point[moving]]]
            self.point_alive[drop_ids[ok]] = False
            merged += int(ok.sum())
        return merged

    def filter_points(
        self, max_error_px: float, min_angle_deg: float, point_ids: np.ndarray | None = None,
        relative_sigma: np.ndarray | None = None, ceiling_px: float = np.inf,
    ) -> int:
        """Drop observations reprojecting beyond max_error_px (two-view points: TWO_VIEW_ERROR_FACTOR times
        that; with `relative_sigma`, one per track observation, that times its relative std-dev, at most
        ceiling_px) or behind their camera, then points with fewer than two observations or a triangulation
        angle below min_angle_deg. Returns the number of observations removed."""
        selected = self._live_points(point_ids)
        used = self.used_observations()
        before = len(used)
        used = used[selected[self.obs_point[used]]]
        two_view = self.point_observation_counts()[self.obs_point[used]] == 2
        limit = np.where(two_view, TWO_VIEW_ERROR_FACTOR * max_error_px, max_error_px)
        if relative_sigma is not None:
            limit = np.minimum(limit * relative_sigma.take(used), np.maximum(limit, ceiling_px))
        self.remove_observations(used[self.errors(used) > limit])
        candidates = np.flatnonzero(selected & self.point_alive)
        self.delete_points(candidates[~self.seen_wide(candidates, min_angle_deg)])
        return before - len(self.used_observations())

    # ------------------------------------------------------------------------------------------ BA

    def bundle_adjust(
        self, config: BundleAdjustmentConfig, variable_images: list[int] | None = None,
        intrinsics_covariance: bool = False, relative_sigma: np.ndarray | None = None,
        hold_intrinsics: bool = False,
    ) -> BundleAdjustmentResult:
        """Global BA (variable_images None: first image fixed, scale by the second) or local BA of the
        points seen by `variable_images`, with the other images that see them held fixed; both refine the
        intrinsics as `refine` says (as COLMAP's local BA does; none with `hold_intrinsics`) and the scene
        adopts them.
        `relative_sigma` (one per track observation): each observation's pixel std-dev as a multiple of
        measurement_sigma_px (None: all alike).

        Returns the adjustment's result (costs, RMS, iterations); the scene holds the adjusted values.
        """
        from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement, bundle_adjust

        used = self.used_observations()
        cameras = list(self.order)
        position = np.full(len(self.registered), -1, np.int64)
        position[cameras] = np.arange(len(cameras))
        fixed, scale_reference = [0], 1
        refine = IntrinsicsRefinement() if hold_intrinsics else self.refine or IntrinsicsRefinement()
        if variable_images is not None:
            used = used.compress(self.points_seen_in(variable_images).take(self.obs_point.take(used)))
            # The images seeing those points that are not variable, in image order (masks: no set operations).
            outside = np.zeros(len(self.registered), bool)
            outside[self.tracks.image_index.take(used)] = True
            outside[np.asarray(variable_images, np.int64)] = False
            if outside.sum() >= 2:
                fixed, scale_reference = position[np.flatnonzero(outside)].tolist(), None
        point_of_obs = self.obs_point.take(used)
        in_adjustment = np.zeros(len(self.point_alive), bool)
        in_adjustment[point_of_obs] = True
        point_ids = np.flatnonzero(in_adjustment)
        point_index = (np.cumsum(in_adjustment) - 1).take(point_of_obs)   # point id -> its rank in point_ids
        result = bundle_adjust(
            [self.cameras[m] for m in cameras], self._poses_of(cameras),
            self.point_xyz.take(point_ids, axis=0), position.take(self.tracks.image_index.take(used)),
            point_index, self.observed_uv.take(used, axis=0), config, fixed_cameras=fixed,
            scale_reference=scale_reference, refine=refine, intrinsics_covariance=intrinsics_covariance,
            relative_sigma=None if relative_sigma is None else relative_sigma.take(used),
        )
        # All rows in one assignment each (89 per-image row writes cost ~0.1 ms a BA).
        self.R[cameras] = np.stack([pose.R for pose in result.poses])
        self.t[cameras] = np.stack([pose.t for pose in result.poses])
        self.point_xyz[point_ids] = result.points
        if refine.refines(self.cameras[0].model):
            refined = dict(zip(cameras, result.cameras, strict=True))
            shared = None if refine.per_image else result.cameras[0]
            self.use_cameras([refined.get(m, shared or camera) for m, camera in enumerate(self.cameras)])
        return result
