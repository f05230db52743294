"""`reconstruct`: images folder in, cameras, points and their files out. The one entry point the CLI
and the REST service call; it orchestrates input, features, the incremental pipeline and the outputs.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimation.config import ReconstructionConfig
from estimation.errors import InputError
from estimation.io.export import transforms_dict, write_colmap_text, write_json, write_ply
from estimation.io.images import ImageSet, find_calibration, list_images, load_rgb
from estimation.io.matchfile import find_match_files, load_match_tracks
from estimation.mapper.incremental import ReprojectionSummary, SparseModel, run_incremental
from estimation.types import ProgressCallback, Tracks

SPARSE_DIR = "sparse"
PLY_NAME = "points.ply"
TRANSFORMS_NAME = "transforms.json"
REPORT_NAME = "report.json"
FIGURES_DIR = "figures"
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


@dataclass(frozen=True)
class ReconstructionResult:
    """What `reconstruct` produced: intrinsics, the sparse model and the report written to out_dir."""

    out_dir: Path
    K: np.ndarray
    width: int
    height: int
    model: SparseModel
    report: dict


@dataclass(frozen=True)
class FeatureTracks:
    """Tracks and where they came from ("matches" files or "sift"), with counts for the report."""

    tracks: Tracks
    source: str
    details: dict


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
    images: ImageSet, config: ReconstructionConfig, progress: ProgressCallback | None = None
) -> FeatureTracks:
    """Multi-view tracks from the course's match files or from SIFT (see `choose_feature_source`)."""
    source = choose_feature_source(images, config.features)
    report = progress or (lambda stage, fraction: None)
    if source == "matches":
        report("reading match files", 0.0)
        parsed = load_match_tracks(images)
        report("reading match files", 1.0)
        details = {"rows": parsed.num_rows, "merged_rows": parsed.num_merged_rows,
                   "rejected_links": parsed.num_rejected_links}
        return FeatureTracks(parsed.tracks, source, details)
    from estimation.features.sift import sift_tracks  # OpenCV is only needed here

    result = sift_tracks(images, config.sift, ransac=config.ransac, progress=report)
    details = {
        "keypoints_per_image": dict(zip(images.names, result.keypoints_per_image, strict=True)),
        "matches_per_pair": {f"{images.names[i]}|{images.names[j]}": n
                             for (i, j), n in result.matches_per_pair.items()},
        "verified_matches_per_pair": {f"{images.names[i]}|{images.names[j]}": n
                                      for (i, j), n in result.verified_per_pair.items()},
        "rejected_links": result.num_rejected_links,
    }
    return FeatureTracks(result.tracks, source, details)


def _error_summary(summary: ReprojectionSummary) -> dict:
    return {"mean": float(summary.mean_px), "median": float(summary.median_px), "rms": float(summary.rms_px),
            "observations": int(summary.num_observations)}


def build_report(
    images: ImageSet,
    K: np.ndarray,
    features: FeatureTracks,
    model: SparseModel,
    seconds: dict[str, float],
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
        "ransac_inliers_per_pair": dict(stats.pair_inliers),
        "initial_pair": list(stats.initial_pair),
        "initial_pair_median_triangulation_angle_deg": float(stats.initial_pair_median_angle_deg),
        "registration_order": [images.names[i] for i in model.registration_order],
        "bundle_adjustment_iterations": int(stats.bundle_adjustment_iterations),
        "seconds_per_stage": seconds,
        "seconds_total": float(sum(seconds.values())),
        "features": {"source": features.source, "tracks": features.tracks.num_tracks,
                     "observations": int(len(features.tracks.track_index)), **features.details},
        "intrinsics": {"K": K.tolist(), "width": images.width, "height": images.height},
        "cameras": [
            {"image": images.names[i], "R": pose.R.tolist(), "t": pose.t.tolist(), "C": pose.center.tolist()}
            for i, pose in sorted(model.poses.items())
        ],
    }


def write_outputs(out_dir: Path, images: ImageSet, K: np.ndarray, model: SparseModel) -> dict[str, Path]:
    """COLMAP text model, coloured PLY and transforms.json (file paths relative to out_dir)."""
    write_colmap_text(
        out_dir / SPARSE_DIR, K, images.width, images.height, images.names, model.poses, model.points,
        model.point_colors, model.point_errors, model.obs_camera, model.obs_point, model.obs_uv,
    )
    write_ply(out_dir / PLY_NAME, model.points, model.point_colors)
    frames = [(os.path.relpath(images.paths[i].resolve(), out_dir.resolve()), pose)
              for i, pose in sorted(model.poses.items())]
    write_json(out_dir / TRANSFORMS_NAME,
               transforms_dict(K, images.width, images.height, frames, ply_file_path=PLY_NAME))
    return {"sparse": out_dir / SPARSE_DIR, "ply": out_dir / PLY_NAME,
            "transforms": out_dir / TRANSFORMS_NAME}


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


@contextmanager
def _timed(seconds: dict[str, float], name: str) -> Iterator[None]:
    """Adds the wall-clock seconds of the block to seconds[name]."""
    start = time.perf_counter()
    yield
    seconds[name] = time.perf_counter() - start


def reconstruct(
    images_dir: Path,
    out_dir: Path,
    config: ReconstructionConfig = ReconstructionConfig(),
    progress: ProgressCallback | None = None,
) -> ReconstructionResult:
    """Structure from Motion of a folder of images; writes sparse/, points.ply, transforms.json,
    report.json and figures/ into out_dir. InputError (naming file, line or reason) on bad input."""
    images_dir, out_dir = Path(images_dir), Path(out_dir)
    seconds: dict[str, float] = {}
    report_input = _scaled(progress, 0.0, PROGRESS_INPUT_END)
    report_input("loading images", 0.0)
    with _timed(seconds, "input"):
        images = list_images(images_dir)
        K = find_calibration(images_dir, config.calibration)
    report_input("loading images", 1.0)

    features_end = PROGRESS_FEATURES_END[choose_feature_source(images, config.features)]
    with _timed(seconds, "features"):
        features = extract_tracks(images, config, _scaled(progress, PROGRESS_INPUT_END, features_end))

    model = run_incremental(features.tracks, K, config,
                            progress=_scaled(progress, features_end, PROGRESS_PIPELINE_END))
    seconds.update({name: float(value) for name, value in model.stats.stage_seconds.items()})

    report_output = _scaled(progress, PROGRESS_PIPELINE_END, 1.0)
    report_output("writing outputs", 0.0)
    out_dir.mkdir(parents=True, exist_ok=True)
    with _timed(seconds, "export"):
        outputs = write_outputs(out_dir, images, K, model)
    if config.write_figures:
        report_output("writing figures", 0.5)
        with _timed(seconds, "figures"):
            outputs.update(write_figures(out_dir, images, model))
    report = build_report(images, K, features, model, seconds)
    report["outputs"] = {name: os.path.relpath(path, out_dir) for name, path in outputs.items()}
    write_json(out_dir / REPORT_NAME, report)
    report_output("finished", 1.0)
    return ReconstructionResult(out_dir=out_dir, K=K, width=images.width, height=images.height,
                                model=model, report=report)
