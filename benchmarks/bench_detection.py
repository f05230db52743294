"""SIFT detection (`features.sift.detect_features`) at several contrast thresholds and detection sizes: CPU
seconds, keypoints, and how well they match.

OpenCV refines a DoG extremum only when |D| > floor(contrast_threshold / 3 * 0.5 * 255) (0..255 units),
which is 0 below 0.02353: every nonzero extremum is then refined. OpenCV's SIFT also doubles the image
before its first octave, so detecting a 3072x2048 photo at `max_image_side` 1600 still samples its finest
scale on the full-size pixel grid, where 3200 builds a 6144x4096 base. For each variant (each
--max-sides value at the default threshold, then each --thresholds value at the default size) the table
gives the CPU seconds of detecting every image in this process (OpenCV on one thread, images decoded
beforehand; the median of --repeats rounds, the variants alternating within each round), the keypoints,
their distinct positions (a keypoint may have several orientations), how many of those lie within
--within px of a position of the first variant, and over every pair of the set's images the matches (ratio
test and mutual check) and the inliers of the verified E (calibration.txt's K). Sets: lego (lego_200 train
+ val composited on white, 90 views of 200x200; no pairs) and fountain (the first three views of
strecha/fountain-P11 at 3072x2048, where the 8192-keypoint budget binds).

    python benchmarks/bench_detection.py
    python benchmarks/bench_detection.py --sets lego --thresholds 0.02,0.0235,0.0236,0.04
    python benchmarks/bench_detection.py --sets fountain --thresholds "" --max-sides 3200,1600,1200
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from itertools import combinations
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sfm import DATA, lego_set  # noqa: E402

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig  # noqa: E402
from estimation.features.matching import match_descriptors  # noqa: E402
from estimation.features.sift import ImageFeatures, detect_features  # noqa: E402
from estimation.io.images import list_images, load_rgb  # noqa: E402
from estimation.two_view.geometry import estimate_two_view_geometry  # noqa: E402

FOUNTAIN = DATA / "strecha" / "fountain-P11"


def images_of(name: str, work: Path) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The set's images and, where pairs are verified, their K."""
    if name == "lego":
        return [load_rgb(path) for path in list_images(lego_set(work).images).paths], None
    views = list_images(FOUNTAIN).paths[:3]
    return [load_rgb(path) for path in views], np.loadtxt(FOUNTAIN / "calibration.txt")


def pair_counts(features: list[ImageFeatures], K: np.ndarray, config: SiftConfig) -> tuple[int, int]:
    """Matches and verified E inliers summed over every pair of the images."""
    matches = inliers = 0
    for a, b in combinations(features, 2):
        pair = match_descriptors(a.descriptors, b.descriptors, config.ratio, config.max_distance)
        geometry = estimate_two_view_geometry(a.uv[pair.index_a], b.uv[pair.index_b], K1=K, K2=K,
                                              config=TwoViewConfig(), ransac=RansacConfig(),
                                              refine_essential=False)
        matches, inliers = matches + len(pair.ratio), inliers + geometry.num_inliers
    return matches, inliers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="lego,fountain", help="comma-separated: lego, fountain")
    parser.add_argument("--thresholds", default="0.02,0.0236", help="comma-separated contrast thresholds")
    parser.add_argument("--max-sides", default="", help="comma-separated max_image_side values")
    parser.add_argument("--within", type=float, default=1.0,
                        help="px: a position counts as found by the first variant this near to one of its")
    parser.add_argument("--repeats", type=int, default=3, help="rounds over the variants (median CPU s)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    variants = [SiftConfig(max_image_side=int(value)) for value in args.max_sides.split(",") if value]
    variants += [SiftConfig(contrast_threshold=float(value)) for value in args.thresholds.split(",") if value]
    print("| set | contrast_threshold | OpenCV's skip | max_image_side | CPU s | keypoints | positions | "
          "near the first's | matches | verified |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as work:
        for name in args.sets.split(","):
            images, K = images_of(name, Path(work))
            seconds: list[list[float]] = [[] for _ in variants]
            detected: list[list[ImageFeatures]] = []
            for _ in range(args.repeats):
                detected = []
                for config, variant_seconds in zip(variants, seconds, strict=True):
                    start = time.process_time()
                    detected.append([detect_features(rgb, config) for rgb in images])
                    variant_seconds.append(time.process_time() - start)
            first = [cKDTree(np.unique(features.uv, axis=0)) for features in detected[0]]
            for config, variant_seconds, features in zip(variants, seconds, detected, strict=True):
                positions = [np.unique(f.uv, axis=0) for f in features]
                near = sum(int((tree.query(uv)[0] <= args.within).sum())
                           for tree, uv in zip(first, positions, strict=True))
                matches, verified = ("-", "-") if K is None else pair_counts(features, K, config)
                skip = int(np.floor(config.contrast_threshold / 3 * 0.5 * 255))
                print(f"| {name} ({len(images)}) | {config.contrast_threshold} | abs(D) <= {skip} | "
                      f"{config.max_image_side} | {np.median(variant_seconds):.2f} | "
                      f"{sum(len(f.uv) for f in features)} | {sum(len(uv) for uv in positions)} | {near} | "
                      f"{matches} | {verified} |", flush=True)


if __name__ == "__main__":
    main()
