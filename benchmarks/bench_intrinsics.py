"""Self-calibration: the same image sets reconstructed with and without calibration.txt; prints a table.

For each Strecha set (3072x2048 JPEGs without EXIF; or lego_200, principal point at the centre, built as
bench_sfm.py does), the images are copied into a temporary folder
once with calibration.txt (K fixed, pinhole) and once without (focal length from the 1.2 * max(w, h)
prior, refined with the camera model's distortion and, by default, the principal point). Printed per
run: registered images, the recovered focal length against the ground truth's (mean of fx and fy), the
principal point's error and its 1-sigma from the final BA's marginal covariance (how well the views
determine it), mean and max rotation error and mean camera-centre error after similarity alignment to
the ground-truth poses, RMS reprojection error, and seconds.

`--synthetic` instead runs the mapper on synthetic scenes with known cameras and a principal point off
the image centre (the split on which the uncalibrated defaults were chosen; the Strecha sets are the
unseen check): each intrinsics setting's recovered focal length, principal point and rotation error.

    python benchmarks/bench_intrinsics.py
    python benchmarks/bench_intrinsics.py --sets fountain-P11 --camera-model radial
    python benchmarks/bench_intrinsics.py --sets lego --uncalibrated-only
    python benchmarks/bench_intrinsics.py --synthetic
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_sfm import IMAGE_SUFFIXES, BenchSet, lego_set, strecha_set

from estimation import ReconstructionConfig, reconstruct
from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement
from estimation.config import CameraConfig
from estimation.geometry.alignment import aligned_pose_errors
from estimation.geometry.projection import Camera
from estimation.mapper.incremental import run_incremental
from estimation.synthetic import SyntheticScene, make_object_scene, make_scene


def principal_point_sigma(sigma: dict[str, float]) -> str:
    """'sigma_cx, sigma_cy' of a refined principal point (the BA's marginal covariance), '-' if held."""
    return f"{sigma['cx']:.1f}, {sigma['cy']:.1f}" if "cx" in sigma else "-"


def run(bench: BenchSet, calibrated: bool, camera_model: str, principal_point: bool | None) -> dict:
    """One reconstruction of the set's images (with or without its calibration.txt) and its errors."""
    truth, true_K = bench.truth, bench.K
    true_focal = (true_K[0, 0] + true_K[1, 1]) / 2
    with tempfile.TemporaryDirectory(prefix="bench_intrinsics_") as work:
        images = Path(work) / "images"
        images.mkdir()
        for path in sorted(bench.images.iterdir()):
            if path.suffix.lower() in IMAGE_SUFFIXES:
                shutil.copy(path, images / path.name)
        if calibrated:
            np.savetxt(images / "calibration.txt", bench.K)
        camera_config = CameraConfig(model="auto" if calibrated else camera_model,
                                     refine_principal_point=principal_point)
        config = ReconstructionConfig(write_figures=False, camera=camera_config)
        start = time.perf_counter()
        result = reconstruct(images, Path(work) / "out", config)
        seconds = time.perf_counter() - start
    report = result.report
    names = report["registration_order"]
    estimated = [result.model.poses[result.model.image_names.index(name)] for name in names]
    errors = aligned_pose_errors(estimated, [truth[name] for name in names])
    camera = report["intrinsics"].get("camera", {})
    focal = (camera.get("fx", np.nan) + camera.get("fy", np.nan)) / 2
    return {
        "registered": f"{report['images_registered']}/{report['images_total']}",
        "focal": focal, "focal_error_pct": 100 * (focal - true_focal) / true_focal,
        "principal_point_error_px": float(np.hypot(camera.get("cx", np.nan) - true_K[0, 2],
                                                   camera.get("cy", np.nan) - true_K[1, 2])),
        "principal_point_sigma_px": principal_point_sigma(camera.get("sigma", {})),
        "k1": camera.get("k1", 0.0), "k2": camera.get("k2", 0.0),
        "rotation_mean_deg": float(errors.rotation_deg.mean()),
        "rotation_max_deg": float(errors.rotation_deg.max()),
        "center_mean": float(errors.center.mean()),
        "rms_px": report["reprojection_error_px"]["after_ba"]["rms"], "seconds": seconds,
    }


SYNTHETIC_WIDTH, SYNTHETIC_HEIGHT = 3072, 2048
SYNTHETIC_TRUTH = Camera("pinhole", fx=2760.0, fy=2765.0, cx=1535.5 + 18.0, cy=1023.5 - 12.0)
"""Strecha-sized photos with a slightly non-square pixel and the principal point 21.6 px off the centre."""


def synthetic_scenes() -> dict[str, SyntheticScene]:
    """Two façade arcs (cameras a few degrees apart, as in fountain-P11 and Herz-Jesus-P8) with the
    principal point off-centre, and an object ring with it at the centre (as lego's)."""
    common = {"num_points": 1500, "noise_px": 0.5, "outlier_fraction": 0.05, "visibility": 0.6,
              "width": SYNTHETIC_WIDTH, "height": SYNTHETIC_HEIGHT, "camera": SYNTHETIC_TRUTH}
    return {
        "arc 11 views 10 deg apart, pp off": make_scene(num_cameras=11, seed=21, arc_step_deg=10.0, **common),
        "arc 8 views 6 deg apart, pp off": make_scene(num_cameras=8, seed=22, arc_step_deg=6.0, **common),
        "object ring 24 views, pp centred": make_object_scene(num_cameras=24, noise_px=0.5, seed=23),
    }


ALWAYS_KEPT = {"principal_point_min_d2": 0.0}
SYNTHETIC_SETTINGS = {
    "true K, fixed": None,
    "simple-radial, pp held": ("simple-radial", False, {}),
    "opencv, pp refined": ("opencv", True, ALWAYS_KEPT),
    "pinhole, pp refined": ("pinhole", True, ALWAYS_KEPT),
    "simple-radial, pp refined from the first BA": (
        "simple-radial", True, {**ALWAYS_KEPT, "principal_point_in_final_rounds_only": False}),
    "simple-radial, pp refined in the final rounds": ("simple-radial", True, ALWAYS_KEPT),
    "simple-radial, pp refined in the final rounds, kept if significant (default)": (
        "simple-radial", True, {}),
}
"""Intrinsics setting -> (camera model, principal point refined, CameraConfig fields changed from their
defaults); None: the true camera held fixed."""


def run_synthetic(scene: SyntheticScene, setting: tuple[str, bool, dict] | None) -> dict:
    """The mapper from COLMAP's prior (1.2 max(w, h), principal point at the centre), or from the truth."""
    config = ReconstructionConfig(write_figures=False)
    if setting is None:
        camera, refine = scene.camera, IntrinsicsRefinement()
    else:
        model, principal_point, camera_fields = setting
        config = config.model_copy(update={"camera": config.camera.model_copy(update=camera_fields)})
        focal = 1.2 * max(scene.width, scene.height)
        camera = Camera(model, fx=focal, fy=focal, cx=(scene.width - 1) / 2, cy=(scene.height - 1) / 2)
        refine = IntrinsicsRefinement(focal=True, distortion=True, principal_point=principal_point)
    start = time.process_time()
    model = run_incremental(scene.tracks, camera, config, refine=refine)
    images = list(model.poses)
    errors = aligned_pose_errors([model.poses[m] for m in images], [scene.poses[m] for m in images])
    refined, truth = model.cameras[images[0]], scene.camera
    return {
        "registered": f"{len(images)}/{len(scene.poses)}",
        "focal_error_pct": 100 * ((refined.fx + refined.fy) / (truth.fx + truth.fy) - 1),
        "principal_point_error_px": float(np.hypot(refined.cx - truth.cx, refined.cy - truth.cy)),
        "principal_point_sigma_px": principal_point_sigma(model.stats.intrinsics_sigma),
        "rotation_mean_deg": float(errors.rotation_deg.mean()),
        "rotation_max_deg": float(errors.rotation_deg.max()), "cpu_seconds": time.process_time() - start,
    }


def main_synthetic() -> None:
    print("| scene | intrinsics | registered | focal err % | pp err px | pp sigma px | rot mean deg "
          "| rot max deg | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene_name, scene in synthetic_scenes().items():
        for setting_name, setting in SYNTHETIC_SETTINGS.items():
            row = run_synthetic(scene, setting)
            print(f"| {scene_name} | {setting_name} | {row['registered']} | {row['focal_error_pct']:+.3f} "
                  f"| {row['principal_point_error_px']:.2f} | {row['principal_point_sigma_px']} "
                  f"| {row['rotation_mean_deg']:.4f} "
                  f"| {row['rotation_max_deg']:.4f} | {row['cpu_seconds']:.0f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=["fountain-P11", "Herz-Jesus-P8"],
                        help="Strecha sets, or lego (lego_200 train + val, principal point at the centre)")
    parser.add_argument("--camera-model", default="simple-radial",
                        choices=["pinhole", "simple-radial", "radial", "opencv"],
                        help="camera model of the uncalibrated runs")
    parser.add_argument("--principal-point", choices=["auto", "refined", "fixed"], default="auto",
                        help="uncalibrated runs: cx, cy as CameraConfig's default (auto), refined, or held "
                             "at the image centre")
    runs = parser.add_mutually_exclusive_group()
    runs.add_argument("--uncalibrated-only", action="store_true", help="skip the runs with calibration.txt")
    runs.add_argument("--calibrated-only", action="store_true", help="skip the runs without calibration.txt")
    parser.add_argument("--synthetic", action="store_true",
                        help="synthetic scenes with an off-centre principal point, not the Strecha sets")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()}")
    if args.synthetic:
        main_synthetic()
        print(f"load average {os.getloadavg()}")
        return
    print("| set | calibration | registered | focal px | focal err % | pp err px | pp sigma px | k1 | k2 "
          "| rot mean deg | rot max deg | centre mean m | RMS px | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="bench_intrinsics_sets_") as work:
        for name in args.sets:
            bench = lego_set(Path(work)) if name == "lego" else strecha_set(name, Path(work))
            run_set(bench, args)
    print(f"load average {os.getloadavg()}")


def run_set(bench: BenchSet, args: argparse.Namespace) -> None:
    """The set's table rows: with calibration.txt, then without (unless --*-only says otherwise)."""
    name = bench.name
    runs = (False,) if args.uncalibrated_only else (True,) if args.calibrated_only else (True, False)
    for calibrated in runs:
        principal_point = {"auto": None, "refined": True, "fixed": False}[args.principal_point]
        row = run(bench, calibrated, args.camera_model, principal_point)
        label = "calibration.txt" if calibrated else f"none ({args.camera_model}, pp {args.principal_point})"
        print(f"| {name} | {label} | {row['registered']} | {row['focal']:.1f} "
              f"| {row['focal_error_pct']:+.2f} | {row['principal_point_error_px']:.1f} "
              f"| {row['principal_point_sigma_px']} | {row['k1']:+.4f} | {row['k2']:+.4f} "
              f"| {row['rotation_mean_deg']:.3f} | {row['rotation_max_deg']:.3f} | {row['center_mean']:.4f} "
              f"| {row['rms_px']:.3f} | {row['seconds']:.0f} |", flush=True)

if __name__ == "__main__":
    main()
