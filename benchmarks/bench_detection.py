"""SIFT detection (`features.sift.detect_features`) at several contrast thresholds: CPU seconds and keypoints.

OpenCV refines a DoG extremum only when |D| > floor(contrast_threshold / 3 * 0.5 * 255) (0..255 units),
which is 0 below 0.02353: every nonzero extremum is then refined. For each threshold the table gives the
CPU seconds of detecting every image in this process (OpenCV on one thread, images decoded beforehand;
the median of --repeats rounds, the thresholds alternating within each round), the keypoints, their
distinct positions (a keypoint may have several orientations) and how many of those the first
threshold's detection also found. Sets: lego (lego_200 train + val composited on white, 90 views of
200x200) and fountain (the first two views of strecha/fountain-P11 at 3072x2048, where the 8192-keypoint
budget binds).

    python benchmarks/bench_detection.py
    python benchmarks/bench_detection.py --sets lego --thresholds 0.02,0.0235,0.0236,0.04
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sfm import DATA, lego_set  # noqa: E402

from estimation.config import SiftConfig  # noqa: E402
from estimation.features.sift import detect_features  # noqa: E402
from estimation.io.images import list_images, load_rgb  # noqa: E402


def images_of(name: str, work: Path) -> list[np.ndarray]:
    if name == "lego":
        return [load_rgb(path) for path in list_images(lego_set(work).images).paths]
    return [load_rgb(path) for path in list_images(DATA / "strecha" / "fountain-P11").paths[:2]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="lego,fountain", help="comma-separated: lego, fountain")
    parser.add_argument("--thresholds", default="0.02,0.0236", help="comma-separated contrast thresholds")
    parser.add_argument("--repeats", type=int, default=3, help="rounds over the thresholds (median CPU s)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    thresholds = [float(value) for value in args.thresholds.split(",")]
    print("| set | contrast_threshold | OpenCV's skip | CPU s | keypoints | positions | "
          "also found at the first |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as work:
        for name in args.sets.split(","):
            images = images_of(name, Path(work))
            seconds: dict[float, list[float]] = {threshold: [] for threshold in thresholds}
            detected: dict[float, list[np.ndarray]] = {}
            for _ in range(args.repeats):
                for threshold in thresholds:
                    config = SiftConfig(contrast_threshold=threshold)
                    start = time.process_time()
                    detected[threshold] = [detect_features(rgb, config).uv for rgb in images]
                    seconds[threshold].append(time.process_time() - start)
            reference: list[set] | None = None
            for threshold in thresholds:
                keypoints = detected[threshold]
                found = [{tuple(uv) for uv in image_uv} for image_uv in keypoints]
                reference = reference or found
                common = sum(len(a & b) for a, b in zip(found, reference, strict=True))
                skip = int(np.floor(threshold / 3 * 0.5 * 255))
                print(f"| {name} ({len(images)}) | {threshold} | abs(D) <= {skip} | "
                      f"{np.median(seconds[threshold]):.2f} | {sum(len(uv) for uv in keypoints)} | "
                      f"{sum(len(positions) for positions in found)} | {common} |", flush=True)

if __name__ == "__main__":
    main()
