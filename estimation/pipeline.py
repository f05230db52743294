"""The Structure from Motion pipeline, `reconstruct`: images folder in, cameras, points and their files out.
The one entry point the CLI and the REST service call (as `estimation.reconstruct`); it orchestrates input,
features, the incremental mapper and the outputs.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from estimation.artefacts import (
    DEPTHS_NAME,
    FIGURES_DIR,
    FRAMES_DIR,
    MODELS_DIR,
    PLY_NAME,
    REPORT_NAME,
    SPARSE_DIR,
    TRANSFORMS_NAME,
)
from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement, along_ray_sigmas, bundle_adjust
from estimation.calibration.self_calibration import focal_from_fundamentals
from estimation.config import BundleAdjustmentConfig, CameraConfig, ReconstructionConfig
from estimation.errors import DegenerateConfigurationError, InputError
from estimation.features.view_graph import (
    LookAlikes,
    PairRotations,
    adopted_pairs,
    is_adopted,
    look_alikes_under,
    registered_pairs,
)
from estimation.geometry.projection import Camera, CameraInput
from estimation.io.export import (
    DepthObservations,
    transforms_dict,
    write_colmap_text,
    write_depths,
    write_json,
    write_ply,
)
from estimation.io.images import (
    ExifFocal,
    ImageSet,
    exif_focal,
    find_calibration,
    find_distortion,
    list_images,
    load_rgb,
)
from estimation.io.matchfile import find_match_files, load_match_tracks
from estimation.io.video import VideoKeyframes, extract_keyframes, is_video
from estimation.mapper.incremental import (
    FoldedModelError,
    ReprojectionSummary,
    SparseModel,
    reconstruct_models,
)
from estimation.mapper.verification import FOLDED, MIRROR_AMBIGUITY
from estimation.types import ProgressCallback, Tracks

if TYPE_CHECKING:
    from estimation.features.planarity import PairTypes
    from estimation.features.sift import FeatureStages, TrackFeatures, VerifiedMatches
    from estimation.two_view.geometry import TwoViewGeometry

FIGURE_NAMES = {
    "initial_pair_matches": "initial_pair_matches.png",
    "triangulation": "triangulation_linear_vs_nonlinear.png",
    "top_view": "cameras_and_points_top_view.png",
}

# Share of the overall progress bar each stage ends at (SIFT detection and matching take far longer
# than reading match files, so the features stage is wider for SIFT).
PROGRESS_INPUT_END = 0.02
PROGRESS_FEATURES_END = {"matches": 0.05, "sift": 0.35}
PROGRESS_PIPELINE_END = 0.93

SIDES_CONFLICTED = "sides of a symmetric object possibly confused"
"""Starts the warning of a model whose look-alike check conflicted (`with_alternatives`)."""

logger = logging.getLogger(__name__)
NO_EXIF = ExifFocal(None, "none", "no EXIF focal length")
FOCAL_FROM_PAIRS = "fundamental matrices"
"""The source of a focal length that `self_calibrated` found (report.json's intrinsics.source)."""


@dataclass(frozen=True)
class InitialIntrinsics:
    """Every image's camera before the reconstruction, where it came from, and what the BA refines."""

    cameras: list[Camera]            # image index -> camera (the same object when shared)
    source: str                      # "calibration file", "exif", "exif and prior", "prior" or
                                     # FOCAL_FROM_PAIRS (`self_calibrated`)
    focal_sources: list[str]         # image index -> "calibration file", an EXIF tag, "prior" or
                                     # FOCAL_FROM_PAIRS
    refine: IntrinsicsRefinement
    warnings: list[str]


@dataclass(frozen=True)
class ReconstructionResult:
    """What `reconstruct` produced: intrinsics, the sparse model and the report written to out_dir."""

    out_dir: Path
    K: np.ndarray                    # the (first registered image's) refined K
    width: int
    height: int
    model: SparseModel               # the largest model (the one written to out_dir)
    report: dict
    models: tuple[SparseModel, ...] = ()   # every model, largest first (models[0] is `model`)


@dataclass(frozen=True)
class FeatureTracks:
    """Tracks and where they came from ("matches" files or "sift"), with counts for the report. With SIFT,
    each verified pair's two-view type by (i, j), i < j (`features.planarity`): with `extract_tracks`'s
    `defer_planarity`, the tests of some may still run until `finished`."""

    tracks: Tracks
    source: str
    details: dict
    pair_types: PairTypes | None = None
    keypoints: TrackFeatures | None = None   # SIFT's keypoints and descriptors (guided 2D-3D matching)
    verified: VerifiedMatches | None = None  # SIFT's verified matches (`fold_check`)
    look_alikes: LookAlikes | None = None    # SIFT's look-alike check under a calibration file (`view_graph`)

    def finished(self) -> FeatureTracks:
        """These tracks with every verified pair's geometry in details["two_view_geometry_per_pair"] (the
        planarity tests waited for, the worker processes ended)."""
        if self.pair_types is None:
            return self
        names = self.tracks.image_names
        per_pair = {f"{names[i]}|{names[j]}": {"type": geometry.type.value, "inliers": geometry.num_inliers,
                                                "h_e_inlier_ratio": round(geometry.h_e_inlier_ratio, 4)}
                    for (i, j), geometry in self.pair_types.geometries().items()}
        return replace(self, details={**self.details, "two_view_geometry_per_pair": per_pair})

    def epipolar_geometries(self) -> dict:
        """Each verified pair's geometry by (i, j), i < j (E, F, inliers), without waiting for the planarity
        tests; empty for match files."""
        return {} if self.pair_types is None else self.pair_types.epipolar_geometries()

    def close(self) -> None:
        """Ends the worker processes of planarity tests still running (`finished` ends them too)."""
        if self.pair_types is not None:
            self.pair_types.close()


def _scaled(progress: ProgressCallback | None, start: float, end: float) -> ProgressCallback:
    """A callback mapping a stage's own fraction 0..1 onto [start, end] of the overall progress."""
    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, start + (end - start) * min(max(fraction, 0.0), 1.0))
    return report


def choose_feature_source(images: ImageSet, features: str) -> str:
    """'matches' or 'sift': `auto` takes the match files when the folder has them."""
    has_match_files = bool(find_match_files(images.folder))
    if features == "matches" and not has_match_files:
        raise InputError(f"{images.folder}: features 'matches' requested, but there is no matching{{i}}.txt")
    if features == "auto":
        return "matches" if has_match_files else "sift"
    return features


def extract_tracks(
    images: ImageSet, config: ReconstructionConfig, progress: ProgressCallback | None = None,
    K: np.ndarray | None = None, defer_planarity: bool = False, stages: FeatureStages | None = None,
    alternative: int | None = None,
) -> FeatureTracks:
    """Multi-view tracks from the course's match files or from SIFT (see `choose_feature_source`); SIFT
    pairs are verified with E when K is given, else with F. `defer_planarity`: the pairs' planarity tests
    (`features.planarity`) run in the front end's worker process beside what the caller does next, until
    the result is `finished` (or `close`d). `stages`: where SIFT's extraction chunks and matching blocks
    run (`features.sift.FeatureStages`; default: this machine's threads and worker processes).
    `alternative` k: where the look-alike check's strongest pairs conflict, the k-th alternative's
    look-alikes are left out (`view_graph.LookAlikes.alternatives`)."""
    source = choose_feature_source(images, config.features)
    report = progress or (lambda stage, fraction: None)
    if source == "matches":
        report("reading match files", 0.0)
        parsed = load_match_tracks(images)
        report("reading match files", 1.0)
        details = {"rows": parsed.num_rows, "merged_rows": parsed.num_merged_rows,
                   "rejected_links": parsed.num_rejected_links}
        return FeatureTracks(parsed.tracks, source, details)
    from estimation.features.planarity import PairTypes
    from estimation.features.sift import sift_pool, sift_tracks  # OpenCV is only needed here

    pool = sift_pool(config.sift)
    try:
        result = sift_tracks(images, config.sift, two_view=config.two_view, ransac=config.ransac, K=K,
                             progress=report, pool=pool, defer_planarity=defer_planarity, stages=stages,
                             alternative=alternative)
    except BaseException:
        pool.shutdown()
        raise
    look_alikes = result.look_alikes
    pair_types = PairTypes(result.two_view, result.untested_uv, K, config.two_view, config.ransac, pool)
    details = {
        "keypoints_per_image": dict(zip(images.names, result.keypoints_per_image, strict=True)),
        "matches_per_pair": {f"{images.names[i]}|{images.names[j]}": n
                             for (i, j), n in result.matches_per_pair.items()},
        "verified_matches_per_pair": {f"{images.names[i]}|{images.names[j]}": n
                                      for (i, j), n in result.verified_per_pair.items()},
        "two_view_geometry_per_pair": {},           # `FeatureTracks.finished`
        "rejected_links": result.num_rejected_links,
        # Verified pairs left out of the tracks as look-alikes, and strongest pairs that conflicted instead.
        "look_alike_pairs": [f"{images.names[i]}|{images.names[j]}" for i, j in look_alikes.pairs],
        "look_alike_conflicts": [f"{images.names[i]}|{images.names[j]}" for i, j in look_alikes.conflicts],
        "look_alike_check": "calibration file" if K is not None else "not run",
        "seconds_per_stage": result.seconds_per_stage,
    }
    # The descriptors stay in memory through the mapping only for guided matching (uint8: 128 B a keypoint).
    keypoints = result.features if config.mapper.guided_matching else None
    features = FeatureTracks(result.tracks, source, details, pair_types, keypoints, result.verified,
                             look_alikes if K is not None else None)
    return features if defer_planarity else features.finished()


class FoldCheck(NamedTuple):
    """The look-alike pairs under one K (`fold_check`), and what `folded` needs."""

    look_alikes: LookAlikes
    rotations: PairRotations     # the verified pairs' relative rotations under that K
    min_adopted: int             # MapperConfig.fold_min_pairs

    @property
    def pairs(self) -> list[tuple[int, int]]:
        """The look-alikes that a folded model adopts: the check's, or where its strongest pairs conflicted,
        those of the rotations that keep them (the first of `LookAlikes.alternatives`)."""
        look_alikes = self.look_alikes
        return list(look_alikes.alternatives[0]) if look_alikes.conflicts else look_alikes.pairs

    def adopted(self, world: np.ndarray) -> str:
        """How many look-alikes world-to-camera rotations (N, 3, 3; NaN: not registered) place as their own
        rotation does, of those between registered images (`view_graph.adopted_pairs`), in words."""
        between = registered_pairs(self.pairs, world)
        adopted = adopted_pairs(self.rotations, between, world)
        return f"{len(adopted)} of the {len(between)} between its images"

    def adopted_by(self, world: np.ndarray) -> bool:
        """Whether rotations (N, 3, 3; NaN: not registered) have adopted the look-alikes
        (`view_graph.is_adopted`): the far side folded onto the near one."""
        return is_adopted(self.rotations, self.pairs, world, self.min_adopted)

    def folded(self, model: SparseModel) -> bool:
        """The model's fold warning, or the look-alikes adopted (`adopted_by`)."""
        return has_warning(model, FOLDED) or self.adopted_by(world_rotations(model))


def has_warning(model: SparseModel, kind: str) -> bool:
    """Whether one of the model's warnings begins with `kind` (`mapper.verification.FOLDED`,
    `MIRROR_AMBIGUITY`)."""
    return any(warning.startswith(kind) for warning in model.warnings)


def can_check_folds(features: FeatureTracks, config: ReconstructionConfig) -> bool:
    """Whether `fold_check` can run: SIFT's verified matches, and the look-alike check on."""
    return features.verified is not None and config.two_view.max_rotation_residual_deg is not None


def fold_check(features: FeatureTracks, K: np.ndarray, config: ReconstructionConfig) -> FoldCheck:
    """The look-alikes with the verified pairs' rotations under K (`view_graph.look_alikes_under`; see
    `can_check_folds`)."""
    rotations, look_alikes = look_alikes_under(K, features.epipolar_geometries(), features.verified.inlier_uv,
                                               len(features.verified.uv), config.two_view)
    return FoldCheck(look_alikes, rotations, config.mapper.fold_min_pairs)


class FirstMappingProbe:
    """The fold probe (`mapper.incremental.FoldProbe`) of a first mapping without a calibration file: the
    look-alikes under the camera of its first global refinement (they barely move as the focal length is
    refined: a rendered box's 172 at 10 % off, 167 at the end; lego_200's 10 and 11), and whether the
    growing model has adopted fold_min_pairs of them since. The last call's camera, rotations and images
    are kept for `unfolded_or_kept`."""

    def __init__(self, features: FeatureTracks, config: ReconstructionConfig) -> None:
        self.features, self.config = features, config
        self.check: FoldCheck | None = None
        self.camera: Camera | None = None
        self.world = np.zeros((0, 3, 3))

    def __call__(self, world: np.ndarray, camera: Camera) -> bool:
        if self.check is None:
            self.check = fold_check(self.features, camera.pinhole().K, self.config)
        self.camera, self.world = camera, world
        return self.check.adopted_by(world)


def world_rotations(model: SparseModel) -> np.ndarray:
    """(N, 3, 3) each image's world-to-camera rotation in the model, NaN where it is not registered."""
    rotations = np.full((len(model.image_names), 3, 3), np.nan)
    for image, pose in model.poses.items():
        rotations[image] = pose.R
    return rotations


def resolve_camera_model(camera: CameraConfig, calibrated: bool, distortion_known: bool = False) -> str:
    """`auto` is pinhole with a calibration file (opencv when a distortion.json comes with it),
    simple-radial (COLMAP's default) without."""
    if camera.model != "auto":
        return camera.model
    if calibrated:
        return "opencv" if distortion_known else "pinhole"
    return "simple-radial"


def initial_intrinsics(images: ImageSet, K: np.ndarray | None, config: CameraConfig,
                       distortion: dict[str, float] | None = None) -> InitialIntrinsics:
    """The cameras to start from: the calibration file's K (held fixed, distortion refined if the
    model has any, unless `distortion` gives it: then everything is held); else each photo's EXIF focal
    length, else focal_prior_factor * max(w, h) with a warning (focal length and distortion refined).
    The principal point is K's (held), or the image centre (refined as `refine_principal_point` says)."""
    model = resolve_camera_model(config, K is not None, distortion is not None)
    per_image = not config.single_camera
    principal_point = (not per_image if config.refine_principal_point is None
                       else config.refine_principal_point)
    if K is not None:
        camera = Camera.from_K(K, "opencv", **(distortion or {})).as_model(model)
        return InitialIntrinsics(
            cameras=[camera] * len(images),
            source="calibration file" + (" and distortion.json" if distortion is not None else ""),
            focal_sources=["calibration file"] * len(images),
            refine=IntrinsicsRefinement(focal=False, distortion=distortion is None, per_image=per_image),
            warnings=[],
        )
    prior_px = config.focal_prior_factor * max(images.width, images.height)
    fov = (config.min_field_of_view_deg, config.max_field_of_view_deg)
    exif = [exif_focal(path, fov) if config.use_exif else NO_EXIF for path in images.paths]
    focals = [e.focal_px for e in exif]
    found = [f for f in focals if f is not None]
    focal_sources = [e.source if e.focal_px is not None else "prior" for e in exif]
    warnings = [f"{name}: EXIF focal length ignored: {e.problem}"
                for name, e in zip(images.names, exif, strict=True)
                if e.problem not in (None, NO_EXIF.problem)]
    missing = [name for name, f in zip(images.names, focals, strict=True) if f is None]
    if not found:
        warnings.append(f"no calibration file and no usable EXIF focal length: focal length prior "
                        f"{config.focal_prior_factor:g} * max(width, height) = {prior_px:.1f} px, refined "
                        "by the bundle adjustment")
    elif missing:
        start = f"the prior {prior_px:.1f} px" if per_image else "the median of the other photos' EXIF"
        warnings.append(f"no usable EXIF focal length in {', '.join(missing)}: starting from {start}")
    for warning in warnings:
        logger.warning(warning)

    def camera_of(focal: float) -> Camera:
        return Camera(model, fx=focal, fy=focal, cx=(images.width - 1) / 2, cy=(images.height - 1) / 2)

    if per_image:
        cameras = [camera_of(f if f is not None else prior_px) for f in focals]
    else:
        cameras = [camera_of(float(np.median(found)) if found else prior_px)] * len(images)
    source = "prior" if not found else "exif" if not missing else "exif and prior"
    return InitialIntrinsics(cameras=cameras, source=source, focal_sources=focal_sources,
                             refine=IntrinsicsRefinement(focal=True, distortion=True, per_image=per_image,
                                                         principal_point=principal_point),
                             warnings=warnings)


def self_calibrated(initial: InitialIntrinsics, geometries: dict[tuple[int, int], TwoViewGeometry],
                    config: ReconstructionConfig) -> InitialIntrinsics:
    """`initial` with the focal length of the verified pairs' F (`self_calibration.focal_from_fundamentals`,
    pairs with verify_pair_min_inliers or more) when it came from the prior alone for a shared camera and
    the pairs determine one (focal_from_pairs); else `initial` as it is."""
    camera = config.camera
    if initial.source != "prior" or initial.refine.per_image or not camera.focal_from_pairs:
        return initial
    pairs = [geometry for geometry in geometries.values()
             if geometry.F is not None and geometry.num_inliers >= config.mapper.verify_pair_min_inliers]
    start = initial.cameras[0]
    found = focal_from_fundamentals(np.array([geometry.F for geometry in pairs]),
                                    np.array([geometry.num_inliers for geometry in pairs]),
                                    (start.cx, start.cy), start.fx, camera.focal_search_factor,
                                    camera.focal_min_contrast)
    if found.focal_px is None:
        logger.info("focal length prior kept: %s", found.reason)
        return initial
    note = (f"starting from {found.focal_px:.1f} px instead of the prior: the focal length that makes the "
            f"{found.pairs} strongest verified pairs' fundamental matrices most nearly essential")
    logger.warning(note)
    cameras = [replace(start, fx=found.focal_px, fy=found.focal_px)] * len(initial.cameras)
    return replace(initial, cameras=cameras, source=FOCAL_FROM_PAIRS,
                   focal_sources=[FOCAL_FROM_PAIRS] * len(cameras), warnings=[*initial.warnings, note])


def _error_summary(summary: ReprojectionSummary) -> dict:
    return {"mean": float(summary.mean_px), "median": float(summary.median_px), "rms": float(summary.rms_px),
            "observations": int(summary.num_observations)}


def _registered_cameras(model: SparseModel) -> list[Camera]:
    """The refined camera of each registered image, in image order."""
    return [model.cameras[i] for i in sorted(model.poses)]


def intrinsics_report(images: ImageSet, initial: InitialIntrinsics, model: SparseModel) -> dict:
    """report.json's intrinsics: the refined camera(s) (OpenCV pixel convention), their source,
    what was refined, the 1-sigma of the refined shared camera (`camera.sigma`: marginal covariance of
    the final BA at the measured pixel noise), whether the refined principal point's shift was significant
    enough to keep (`principal_point_test`; if not, it is back at the centre and `refined` says False) and
    the warnings."""
    cameras = _registered_cameras(model)
    report = {
        "K": cameras[0].K.tolist(), "width": images.width, "height": images.height,
        "model": cameras[0].model, "source": initial.source,
        "refined": {"focal_length": initial.refine.focal, "principal_point": initial.refine.principal_point,
                    "distortion": initial.refine.distortion and cameras[0].model != "pinhole"},
        "single_camera": not initial.refine.per_image,
        "pixel_convention": "centre of the top-left pixel at (0, 0) (OpenCV); COLMAP files add 0.5",
        "warnings": list(initial.warnings),
    }
    if initial.refine.per_image:
        report["cameras"] = {images.names[i]: {**model.cameras[i].to_dict(),
                                               "initial_focal_px": float(initial.cameras[i].fx),
                                               "focal_source": initial.focal_sources[i]}
                             for i in sorted(model.poses)}
    else:
        report["camera"] = {**cameras[0].to_dict(), "initial_focal_px": float(initial.cameras[0].fx),
                            "sigma": dict(model.stats.intrinsics_sigma)}
    test = model.stats.principal_point_test
    if test is not None:
        report["refined"]["principal_point"] = test.kept
        report["principal_point_test"] = {"shift_px": list(test.shift_px), "sigma_px": list(test.sigma_px),
                                          "d2": test.d2, "kept": test.kept}
        report["focal_sources"] = dict(zip(images.names, initial.focal_sources, strict=True))
    return report


def model_summary(images: ImageSet, model: SparseModel) -> dict:
    """One model in report.json's `models` list: its images, points and how it started and ended."""
    num_points = int(len(model.points))
    stats = model.stats
    return {
        "images_registered": len(model.poses),
        "images": [images.names[i] for i in model.registration_order],
        "points": num_points,
        "mean_track_length": float(np.bincount(model.obs_point).mean()) if num_points else 0.0,
        "initial_pair": list(stats.initial_pair),
        "initial_pair_failures": dict(stats.initial_pair_failures),
        "reprojection_error_px": _error_summary(stats.reprojection_after_ba),
        "refinement_rounds": int(stats.refinement_rounds),
        "relaxed_thresholds": bool(stats.relaxed_thresholds),
        "final_ba_relative_cost_decrease": float(stats.final_cost_decrease),
        "noise_sigma_px": float(stats.noise_sigma_px),
        "reprojection_limit_px": float(stats.reprojection_limit_px),
        "merged_models": list(stats.merged_models),
        "guided_registrations": dict(stats.guided_registrations),
        "registration_rotation_std_deg": dict(stats.registration_rotation_std_deg),
        "warnings": list(model.warnings),
    }


def build_report(
    images: ImageSet,
    initial: InitialIntrinsics,
    features: FeatureTracks,
    model: SparseModel,
    seconds: dict[str, float],
    models: tuple[SparseModel, ...] = (),
) -> dict:
    """The report.json content: counts, errors before/after BA, inliers per pair, timings, cameras."""
    stats = model.stats
    num_points = int(len(model.points))
    track_lengths = np.bincount(model.obs_point, minlength=num_points) if num_points else np.zeros(0)
    return {
        "images_total": len(images),
        "images_registered": len(model.poses),
        "unregistered": [{"image": images.names[i], "reason": reason}
                         for i, reason in sorted(model.unregistered.items())],
        "points": num_points,
        "observations": int(len(model.obs_point)),
        "mean_track_length": float(track_lengths.mean()) if num_points else 0.0,
        "reprojection_error_px": {
            "before_ba": _error_summary(stats.reprojection_before_ba),
            "after_ba": _error_summary(stats.reprojection_after_ba),
        },
        "shared_tracks_per_pair": dict(stats.pair_shared_tracks),
        "initial_pair": list(stats.initial_pair),
        "initial_pair_median_triangulation_angle_deg": float(stats.initial_pair_median_angle_deg),
        "registration_order": [images.names[i] for i in model.registration_order],
        "bundle_adjustment_iterations": int(stats.bundle_adjustment_iterations),
        "models": [model_summary(images, each) for each in (models or (model,))],
        "seconds_per_stage": seconds,
        "seconds_total": float(sum(seconds.values())),
        "features": {"source": features.source, "tracks": features.tracks.num_tracks,
                     "observations": int(len(features.tracks.track_index)), **features.details},
        "intrinsics": intrinsics_report(images, initial, model),
        "warnings": list(initial.warnings) + list(model.warnings),
        "registration_checks": [{"image": images.names[check.image], "event": check.event,
                                 "reason": check.reason} for check in model.checks],
        "cameras": [
            {"image": images.names[i], "R": pose.R.tolist(), "t": pose.t.tolist(), "C": pose.center.tolist()}
            for i, pose in sorted(model.poses.items())
        ],
    }


def write_outputs(out_dir: Path, images: ImageSet, model: SparseModel, single_camera: bool
                  ) -> dict[str, Path]:
    """COLMAP text model, coloured PLY and transforms.json (file paths relative to out_dir), with the
    refined camera (one shared, or one per image)."""
    registered = _registered_cameras(model)
    write_colmap_text(
        out_dir / SPARSE_DIR, registered[0] if single_camera else model.cameras, images.width, images.height,
        images.names, model.poses, model.points, model.point_colors, model.point_errors, model.obs_camera,
        model.obs_point, model.obs_uv,
    )
    write_ply(out_dir / PLY_NAME, model.points, model.point_colors)
    frames = [(os.path.relpath(images.paths[i].resolve(), out_dir.resolve()), pose)
              for i, pose in sorted(model.poses.items())]
    write_json(out_dir / TRANSFORMS_NAME,
               transforms_dict(registered[0], images.width, images.height, frames, ply_file_path=PLY_NAME,
                               frame_cameras=None if single_camera else registered))
    return {"sparse": out_dir / SPARSE_DIR, "ply": out_dir / PLY_NAME,
            "transforms": out_dir / TRANSFORMS_NAME}


def write_depths_file(out_dir: Path, images: ImageSet, model: SparseModel, config: BundleAdjustmentConfig
                      ) -> Path:
    """depths.npz (`export.write_depths`): every observation's point and its std-dev along the viewing ray,
    from the point marginals of one more BA iteration on the final model (converged: it barely moves), its
    gauge held hard (first camera, scale) so that they are relative to the cameras, scaled to the measured
    noise."""
    order = sorted(model.poses)
    position = np.full(len(images.names), -1, np.int64)
    position[order] = np.arange(len(order))
    # One iteration: the final model is converged; more moved its std-devs by under 0.2 % (lego) for 0.1 s.
    hard_gauge = config.model_copy(update={"scale_sigma_relative": config.fixed_camera_sigma,
                                           "max_iterations": 1})
    result = bundle_adjust([model.cameras[m] for m in order], [model.poses[m] for m in order], model.points,
                           position[model.obs_camera], model.obs_point, model.obs_uv, hard_gauge,
                           point_covariances=True)
    noise = result.measured_pixel_sigma
    covariances = result.point_covariances * (noise / config.measurement_sigma_px) ** 2
    centres = np.stack([model.poses[m].center for m in order])[position[model.obs_camera]]
    points = model.points[model.obs_point]
    sigma = along_ray_sigmas(points, centres, covariances[model.obs_point])
    out_dir_resolved = out_dir.resolve()
    file_paths = [os.path.relpath(images.paths[m].resolve(), out_dir_resolved) for m in order]
    depths = DepthObservations(file_paths, position[model.obs_camera], points, sigma, noise)
    write_depths(out_dir / DEPTHS_NAME, depths)
    return out_dir / DEPTHS_NAME


def write_figures(out_dir: Path, images: ImageSet, model: SparseModel) -> dict[str, Path]:
    """The initial pair's matches and triangulation, and the top view of everything, as PNGs."""
    from estimation.io import figures  # matplotlib is only needed here

    folder = out_dir / FIGURES_DIR
    pair = model.initial_pair_diagnostics
    written = {
        "initial_pair_matches": figures.plot_pair_matches(
            load_rgb(images.paths[pair.i]), load_rgb(images.paths[pair.j]), pair.uv_i, pair.uv_j,
            pair.inlier_mask, (images.names[pair.i], images.names[pair.j]),
            folder / FIGURE_NAMES["initial_pair_matches"],
        ),
        "triangulation": figures.plot_triangulation_comparison(
            pair.points_linear, pair.points_nonlinear, folder / FIGURE_NAMES["triangulation"]
        ),
        "top_view": figures.plot_top_view(
            model.poses, model.points, model.point_colors, images.names, folder / FIGURE_NAMES["top_view"]
        ),
    }
    return written


def video_keyframes(path: Path, out_dir: Path, config: ReconstructionConfig,
                    progress: ProgressCallback | None = None) -> VideoKeyframes | None:
    """A video file's keyframes written into out_dir/FRAMES_DIR (`estimation.io.video`), or None when `path`
    is not a video file (a folder of images)."""
    if not is_video(path):
        return None
    return extract_keyframes(path, out_dir / FRAMES_DIR, config.video, progress)


def video_config(config: ReconstructionConfig) -> ReconstructionConfig:
    """`config` for a video's keyframes: pairs along the video plus loop closures (`pair_selection`)."""
    return config.model_copy(update={"sift": config.sift.model_copy(update={"pair_selection": "video"})})


@contextmanager
def _timed(seconds: dict[str, float], name: str) -> Iterator[None]:
    """Adds the wall-clock seconds of the block to seconds[name]."""
    start = time.perf_counter()
    yield
    seconds[name] = time.perf_counter() - start


class Refolding(NamedTuple):
    """What `reconstruct` goes on with after its first mapping was checked for a fold (`unfolded_or_kept`,
    without a calibration file) or its look-alike check conflicted (`with_alternatives`)."""

    features: FeatureTracks
    models: tuple[SparseModel, ...] | None   # None: the first mapping, stopped, is to be run in full
    discarded_seconds: float     # the checks', and the front ends' and the mappings' not kept
    features_seconds: float      # the kept front end's, when it was run again
    warning: str | None = None   # for the largest model, when a folded one is kept


class MappingRun(NamedTuple):
    """A front end and the mapping of its tracks (`run_again`; each that `with_alternatives` compares)."""

    features: FeatureTracks
    models: tuple[SparseModel, ...] | None   # None: no model
    seconds: float               # its front end's (when run again) and its mapping's
    features_seconds: float      # its front end's run again (0: the first mapping's front end)


ALTERNATIVE_WORDS = ("that contradict them", "that the rotations averaged over them put on other sides")
"""How `with_alternatives` names the pairs of each of `LookAlikes.alternatives`."""


def has_conflicts(features: FeatureTracks) -> bool:
    """Whether the look-alike check's strongest pairs conflicted and some alternative has look-alikes to
    leave out (`view_graph.LookAlikes.alternatives`)."""
    return features.look_alikes is not None and any(features.look_alikes.alternatives)


def preference(models: tuple[SparseModel, ...] | None) -> tuple[bool, int, bool]:
    """How `with_alternatives` ranks a mapping: its largest model without a fold warning first, then by its
    registered images, then without a near-mirror warning (no model last)."""
    if models is None:
        return False, 0, False
    largest = models[0]
    return not has_warning(largest, FOLDED), len(largest.poses), not has_warning(largest, MIRROR_AMBIGUITY)


def mapped_words(models: tuple[SparseModel, ...] | None) -> str:
    """What a mapping gave, in words: its largest model's registered images and fold warning."""
    if models is None:
        return "no model"
    warned = ", with a fold warning" if has_warning(models[0], FOLDED) else ""
    return f"{len(models[0].poses)} images registered{warned}"


def with_alternatives(features: FeatureTracks, models: tuple[SparseModel, ...], mapping_seconds: float,
                      extract_alternative: Callable[[int], FeatureTracks],
                      mapped: Callable[[FeatureTracks], tuple[SparseModel, ...]]) -> Refolding:
    """After a first mapping (`models`, in `mapping_seconds`) with every pair in (`has_conflicts`): the front
    end again with each alternative's look-alikes left out (`extract_alternative(k)`) and its mapping
    (`mapped`). The mapping ranked first by `preference` is kept, the earlier on a tie: a model folded onto
    itself cannot close the ring that another registers whole, unless it registers every view folded, and
    then its cameras that coincide share too few points, or some were tried on the other side.
    details["look_alike_conflicts_outcome"] says what each gave, and the kept model's warnings gain
    SIDES_CONFLICTED: any of them may still have cameras on the wrong side."""
    look_alikes, names = features.look_alikes, features.tracks.image_names
    kept, chosen, discarded = MappingRun(features, models, mapping_seconds, 0.0), 0, 0.0
    words = [f"mapped with every pair, {mapped_words(models)}"]
    for k, pairs in enumerate(look_alikes.alternatives):
        if not pairs:
            continue
        started = time.perf_counter()
        candidate_features = extract_alternative(k)
        features_seconds = time.perf_counter() - started
        try:
            candidate: tuple[SparseModel, ...] | None = mapped(candidate_features)
        except DegenerateConfigurationError as error:
            logger.warning("with look-alike alternative %d left out, no model: %s", k, error)
            candidate = None
        except BaseException:
            candidate_features.close()
            raise
        seconds = time.perf_counter() - started
        words.append(f"with the {len(pairs)} pairs {ALTERNATIVE_WORDS[k]} left out, "
                     f"{mapped_words(candidate)}")
        if preference(candidate) > preference(kept.models):
            kept.features.close()
            discarded += kept.seconds
            kept, chosen = MappingRun(candidate_features, candidate, seconds, features_seconds), k + 1
        else:
            candidate_features.close()
            discarded += seconds
    conflicts = ", ".join(f"{names[i]}|{names[j]}" for i, j in look_alikes.conflicts)
    found = (f"strongest pairs conflicted ({conflicts}): {'; '.join(words)}: the "
             f"{('first', 'second', 'third')[chosen]} kept")
    kept.models[0].warnings.append(
        f"{SIDES_CONFLICTED}: the look-alike check's {found}; views this far apart may not tell the object's "
        "sides apart, so some cameras may sit on the wrong side")
    details = {**kept.features.details, "look_alike_conflicts_outcome": found}
    return Refolding(replace(kept.features, details=details), kept.models, discarded, kept.features_seconds)


def run_again(extract: Callable[[np.ndarray, int | None], FeatureTracks],
              mapped: Callable[[FeatureTracks, Camera], tuple[SparseModel, ...]], camera: Camera
              ) -> MappingRun | None:
    """The front end under camera's K (`extract(K, alternative)`) and the mapping from `camera` (`mapped`),
    again with the alternatives where the look-alike check's strongest pairs conflicted
    (`with_alternatives`); None (the reason logged) when they build no model."""
    started = time.perf_counter()
    K = camera.pinhole().K
    features = extract(K, None)
    features_seconds = time.perf_counter() - started
    try:
        mapping_started = time.perf_counter()
        models = mapped(features, camera)
        if has_conflicts(features):
            resolved = with_alternatives(features, models, time.perf_counter() - mapping_started,
                                         lambda k: extract(K, k), lambda tracks: mapped(tracks, camera))
            features, models = resolved.features, resolved.models
            features_seconds += resolved.features_seconds
        return MappingRun(features, models, time.perf_counter() - started, features_seconds)
    except DegenerateConfigurationError as error:
        logger.warning("run again after a folded model, no model: %s", error)
        features.close()
        return None
    except BaseException:
        features.close()
        raise


def unfolded_or_kept(features: FeatureTracks, models: tuple[SparseModel, ...] | None, mapping_seconds: float,
                     probe: FirstMappingProbe, extract: Callable[[np.ndarray, int | None], FeatureTracks],
                     mapped: Callable[[FeatureTracks, Camera], tuple[SparseModel, ...]],
                     config: ReconstructionConfig) -> Refolding:
    """After the first mapping without a calibration file (`models`, mapped in `mapping_seconds`; None when
    `probe` stopped it as folded): when it is folded (`FoldCheck.folded` under its refined K, or the probe's
    finding), the front end (`extract(K, alternative)`: E verification and the look-alike pairs left out
    up front, as with a calibration file) and the mapping (`mapped`) run again under its camera
    (`run_again`), and replace it unless they build no model or a folded one. Refolding.models is None when
    the first mapping was stopped and is wanted after all. details["look_alike_check"] says what happened."""
    started = time.perf_counter()
    if models is not None:
        camera = _registered_cameras(models[0])[0]
        check = fold_check(features, camera.pinhole().K, config)
        folded = check.folded(models[0])
        found = (f"{len(check.pairs)} look-alike pairs under the model's refined focal length, "
                 f"{check.adopted(world_rotations(models[0]))} adopted by it")
    else:
        camera, check, folded = probe.camera, probe.check, True
        registered = int(np.isfinite(probe.world[:, 0, 0]).sum())
        found = (f"{len(check.pairs)} look-alike pairs under the model's first refined focal "
                 f"length, {check.adopted(probe.world)} adopted by it at {registered} images, where its "
                 "mapping stopped")
    outcome, refolding = "kept", Refolding(features, models, time.perf_counter() - started, 0.0)
    if folded:
        # Left out of the F-verified tracks, the look-alikes still left a rendered box folded (other pairs'
        # F inliers joined its sides); verified with E under the refined K, they did not.
        again_started = time.perf_counter()
        again = run_again(extract, mapped, camera)
        if again is not None and not check.folded(again.models[0]):
            features.close()
            outcome = "folded; run again under its refined camera, which replaced it"
            refolding = Refolding(again.features, again.models, again_started - started + mapping_seconds,
                                  again.features_seconds)
        else:
            if again is not None:
                again.features.close()
            what = "folded too" if again is not None else "no model"
            outcome = f"folded; run again under its refined camera, {what}: the first model kept"
            discarded = time.perf_counter() - started + (mapping_seconds if models is None else 0.0)
            warning = f"{FOLDED}: {found}; run again under its refined camera, {what}"
            refolding = Refolding(features, models, discarded, 0.0, warning)
    details = {**refolding.features.details, "look_alike_check": f"{found}: {outcome}"}
    return refolding._replace(features=replace(refolding.features, details=details))


def reconstruct(
    images_dir: Path,
    out_dir: Path,
    config: ReconstructionConfig = ReconstructionConfig(),
    progress: ProgressCallback | None = None,
    stages: FeatureStages | None = None,
) -> ReconstructionResult:
    """Structure from Motion of a folder of images, or of a video's keyframes (`video_keyframes`); writes
    sparse/, points.ply, depths.npz, transforms.json, report.json and figures/ into out_dir. InputError
    (naming file, line or reason) on bad input. `stages`: where SIFT's extraction chunks and matching
    blocks run (`features.sift.FeatureStages`: other machines' workers; default: this machine's threads
    and processes)."""
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    seconds: dict[str, float] = {}
    report_input = _scaled(progress, 0.0, PROGRESS_INPUT_END)
    report_input("loading images", 0.0)
    with _timed(seconds, "input"):
        video = video_keyframes(images_dir, out_dir, config, report_input)
        if video is not None:
            images_dir, config = video.folder, video_config(config)
        images = list_images(images_dir)
        initial = initial_intrinsics(images, find_calibration(images_dir, config.calibration), config.camera,
                                     find_distortion(images_dir, config.calibration))
    report_input("loading images", 1.0)

    features_end = PROGRESS_FEATURES_END[choose_feature_source(images, config.features)]

    def extract(K: np.ndarray | None, report: ProgressCallback, alternative: int | None = None
                ) -> FeatureTracks:
        # The planarity tests run beside the mapper, which leaves the other cores idle.
        return extract_tracks(images, config, report, K=K, defer_planarity=True, stages=stages,
                              alternative=alternative)

    with _timed(seconds, "features"):
        calibration_K = initial.cameras[0].pinhole().K if initial.source == "calibration file" else None
        features = extract(calibration_K, _scaled(progress, PROGRESS_INPUT_END, features_end))

    with _timed(seconds, "self-calibration"):
        initial = self_calibrated(initial, features.epipolar_geometries(), config)

    def mapped(tracks: FeatureTracks, camera: CameraInput, report: ProgressCallback,
               probe: FirstMappingProbe | None = None) -> tuple[SparseModel, ...]:
        return tuple(reconstruct_models(tracks.tracks, camera, config, progress=report, refine=initial.refine,
                                        pair_types=tracks.pair_types, keypoints=tracks.keypoints,
                                        pair_geometries=tracks.epipolar_geometries(), fold_probe=probe))

    def held(why: str) -> ProgressCallback:
        # A run again after the first model holds the bar where the mapping ended.
        def report(stage: str, fraction: float) -> None:
            if progress is not None:
                progress(f"{stage} (again, {why})", PROGRESS_PIPELINE_END)
        return report

    again = held("under the folded model's refined camera")

    start = initial.cameras if initial.refine.per_image else initial.cameras[0]
    # Without a calibration file a fold is looked for while the first model grows, and after it.
    probe = (FirstMappingProbe(features, config) if calibration_K is None and not initial.refine.per_image
             and can_check_folds(features, config) else None)
    try:
        started = time.perf_counter()
        try:
            models = mapped(features, start, _scaled(progress, features_end, PROGRESS_PIPELINE_END), probe)
        except FoldedModelError:
            models = None
        refolding = None
        if probe is not None:
            refolding = unfolded_or_kept(features, models, time.perf_counter() - started, probe,
                                         lambda K, alternative: extract(K, again, alternative),
                                         lambda tracks, camera: mapped(tracks, camera, again), config)
        elif has_conflicts(features):
            alternatives = held("with other look-alikes left out")
            refolding = with_alternatives(features, models, time.perf_counter() - started,
                                          lambda k: extract(calibration_K, alternatives, k),
                                          lambda tracks: mapped(tracks, start, alternatives))
        if refolding is not None:
            features = refolding.features
            models = refolding.models or mapped(features, start, again)
            seconds["features"] += refolding.features_seconds
            seconds["look-alike check"] = refolding.discarded_seconds
            if refolding.warning is not None:
                models[0].warnings.append(refolding.warning)
        features = features.finished()
    finally:
        features.close()
    model = models[0]
    seconds.update({name: float(value) for name, value in model.stats.stage_seconds.items()})

    report_output = _scaled(progress, PROGRESS_PIPELINE_END, 1.0)
    report_output("writing outputs", 0.0)
    out_dir.mkdir(parents=True, exist_ok=True)
    with _timed(seconds, "export"):
        outputs = write_outputs(out_dir, images, model, single_camera=not initial.refine.per_image)
        outputs["depths"] = write_depths_file(out_dir, images, model, config.bundle_adjustment)
        if config.mapper.export_all_models:
            for number, other in enumerate(models[1:], start=2):
                written = write_outputs(out_dir / MODELS_DIR / str(number), images, other,
                                        single_camera=not initial.refine.per_image)
                outputs.update({f"model_{number}_{name}": path for name, path in written.items()})
    if config.write_figures:
        report_output("writing figures", 0.5)
        with _timed(seconds, "figures"):
            outputs.update(write_figures(out_dir, images, model))
    report = build_report(images, initial, features, model, seconds, models)
    if video is not None:
        report["video"] = video.summary()
    report["outputs"] = {name: os.path.relpath(path, out_dir) for name, path in outputs.items()}
    write_json(out_dir / REPORT_NAME, report)
    report_output("finished", 1.0)
    return ReconstructionResult(out_dir=out_dir, K=_registered_cameras(model)[0].K, width=images.width,
                                height=images.height, model=model, report=report, models=models)
