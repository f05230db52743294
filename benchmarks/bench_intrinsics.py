"""Self-calibration: the same image sets reconstructed with and without calibration.txt; prints a table.

For each Strecha set (3072x2048 JPEGs without EXIF), the images are copied into a temporary folder
once with calibration.txt (K fixed, pinhole) and once without (focal length from the 1.2 * max(w, h)
prior, refined with the camera model's distortion by the bundle adjustment). Printed per run:
registered images, the recovered focal length against the ground truth's (mean of fx and fy), mean
and max rotation error and mean camera-centre error after similarity alignment to the ground-truth
poses, RMS reprojection error, and seconds.

    flock /tmp/sfmnerf-bench.lock python benchmarks/bench_intrinsics.py
    python benchmarks/bench_intrinsics.py --sets fountain-P11 --camera-model radial
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from estimation import ReconstructionConfig, reconstruct
from estimation.config import CameraConfig
from estimation.geometry.alignment import aligned_pose_errors
from estimation.types import CameraPose

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "strecha"


def ground_truth(folder: Path) -> tuple[dict[str, CameraPose], np.ndarray]:
    """(image name -> true pose, the first camera's true K)."""
    cameras = json.loads((folder / "ground_truth.json").read_text())["cameras"]
    poses = {name: CameraPose(R=np.array(c["R"]), t=np.array(c["t"])) for name, c in cameras.items()}
    return poses, np.array(next(iter(cameras.values()))["K"])


def run(folder: Path, calibrated: bool, camera_model: str, principal_point: bool | None) -> dict:
    """One reconstruction of the folder's JPEGs (with or without its calibration.txt) and its errors."""
    truth, true_K = ground_truth(folder)
    true_focal = (true_K[0, 0] + true_K[1, 1]) / 2
    with tempfile.TemporaryDirectory(prefix="bench_intrinsics_") as work:
        images = Path(work) / "images"
        images.mkdir()
        for path in sorted(folder.glob("*.jpg")):
            shutil.copy(path, images / path.name)
        if calibrated:
            shutil.copy(folder / "calibration.txt", images / "calibration.txt")
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
        "k1": camera.get("k1", 0.0), "k2": camera.get("k2", 0.0),
        "rotation_mean_deg": float(errors.rotation_deg.mean()),
        "rotation_max_deg": float(errors.rotation_deg.max()),
        "center_mean": float(errors.center.mean()),
        "rms_px": report["reprojection_error_px"]["after_ba"]["rms"], "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of the Strecha sets")
    parser.add_argument("--sets", nargs="+", default=["fountain-P11", "Herz-Jesus-P8"])
    parser.add_argument("--camera-model", default="simple-radial",
                        choices=["pinhole", "simple-radial", "radial", "opencv"],
                        help="camera model of the uncalibrated runs")
    parser.add_argument("--principal-point", choices=["auto", "refined", "fixed"], default="auto",
                        help="uncalibrated runs: cx, cy as CameraConfig's default (auto), refined, or held "
                             "at the image centre")
    parser.add_argument("--uncalibrated-only", action="store_true", help="skip the runs with calibration.txt")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()}")
    print("| set | calibration | registered | focal px | focal err % | pp err px | k1 | k2 | rot mean deg "
          "| rot max deg | centre mean m | RMS px | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.sets:
        for calibrated in (False,) if args.uncalibrated_only else (True, False):
            principal_point = {"auto": None, "refined": True, "fixed": False}[args.principal_point]
            row = run(args.data / name, calibrated, args.camera_model, principal_point)
            label = ("calibration.txt" if calibrated
                     else f"none ({args.camera_model}, pp {args.principal_point})")
            print(f"| {name} | {label} | {row['registered']} | {row['focal']:.1f} "
                  f"| {row['focal_error_pct']:+.2f} | {row['principal_point_error_px']:.1f} "
                  f"| {row['k1']:+.4f} | {row['k2']:+.4f} "
                  f"| {row['rotation_mean_deg']:.3f} "
                  f"| {row['rotation_max_deg']:.3f} | {row['center_mean']:.4f} | {row['rms_px']:.3f} "
                  f"| {row['seconds']:.0f} |", flush=True)
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
