"""Feature extraction + matching + geometric verification, side by side with pycolmap on the same images.

Ours: `estimation.features.sift.sift_tracks` (RootSIFT on the image downscaled to --max-side, batched
numpy matching with ratio test and mutual check, E/F/H verification with the known K); the seconds of
each stage are its own (`seconds_per_stage`: matching and verification are one stage, run together in
the worker processes). pycolmap: `extract_features` (same max image side, same
feature budget, one PINHOLE camera with the same K) + `match_exhaustive` (its matching includes the
two-view verification). Both use every core of the machine. Sets:

- lego: ../shared/data/lego_200 train + val (90 views, 200x200 RGBA composited on white), K from
  camera_angle_x;
- fountain: ../shared/data/strecha/fountain-P11 (11 views, 3072x2048), K from calibration.txt.

On lego it also measures the retrieval used beyond `exhaustive_up_to` images (VLAD, untimed): the share of
the view pairs whose ground-truth viewing directions are within 20 / 30 degrees that the retrieval
neighbours contain, with the vocabulary trained on each cap of --vocabulary-descriptors (0: every
descriptor); --turned also times that training on the views each turned by 90 and 270 degrees as well
(bench_celery_sfm's 270 images).

    python benchmarks/bench_features.py
    python benchmarks/bench_features.py --sets lego --max-side 3200 --max-features 8192
    python benchmarks/bench_features.py --sets lego --vocabulary-descriptors 20000,0,10000 --turned
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig
from estimation.features.pairs import (
    VOCABULARY_TRAINING_DESCRIPTORS,
    exhaustive_pairs,
    retrieval_pairs,
    train_vocabulary,
    vlad,
)
from estimation.features.sift import detect_features, sift_tracks
from estimation.io.images import find_calibration, list_images, load_rgb
from neural.data import load_image

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LEGO_SPLITS = ("train", "val")


def prepare_lego(data: Path, folder: Path) -> np.ndarray:
    """The 90 lego views composited on white as RGB PNGs in `folder`; K (OpenCV pixel centres)."""
    width = None
    for split in LEGO_SPLITS:
        meta = json.loads((data / "lego_200" / f"transforms_{split}.json").read_text())
        for frame in meta["frames"]:
            source = data / "lego_200" / f"{frame['file_path']}.png"
            rgb = np.rint(load_image(source, white_background=True) * 255).astype(np.uint8)
            Image.fromarray(rgb).save(folder / source.name)
            width = rgb.shape[1]
    focal = 0.5 * width / math.tan(0.5 * meta["camera_angle_x"])
    centre = width / 2 - 0.5
    return np.array([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]])


def lego_retrieval_recall(data: Path, folder: Path, config: SiftConfig, vocabulary_descriptors: list[int],
                          turned: bool) -> list[str]:
    """Recall of the VLAD retrieval pairs against ground-truth view-direction neighbours, per k, with the
    vocabulary trained on each of `vocabulary_descriptors` (0: all of them); with `turned`, the seconds of
    that training on the views turned too."""
    images = list_images(folder)
    direction = {}
    for split in LEGO_SPLITS:
        for frame in json.loads((data / "lego_200" / f"transforms_{split}.json").read_text())["frames"]:
            direction[f"{Path(frame['file_path']).name}.png"] = -np.array(frame["transform_matrix"])[:3, 2]
    views = np.stack([direction[name] for name in images.names])
    angle = np.degrees(np.arccos(np.clip(views @ views.T, -1.0, 1.0)))
    descriptors = [detect_features(load_rgb(path), config).descriptors for path in images.paths]
    all_pairs = exhaustive_pairs(len(images))
    close = {limit: {(i, j) for i, j in all_pairs if angle[i, j] < limit} for limit in (20, 30)}
    lines = []
    for cap in vocabulary_descriptors:
        vocabulary = train_vocabulary(descriptors, config.vocabulary_size, cap or sys.maxsize)
        global_descriptors = np.stack([vlad(d, vocabulary) for d in descriptors])
        lines.append(f"vocabulary on {cap or 'all'} of {sum(map(len, descriptors))} descriptors:")
        for k in (10, 20, config.retrieval_neighbours):
            pairs = retrieval_pairs(global_descriptors, k)
            recall = [f"{len(pairs & near) / len(near):.3f} of {len(near)} pairs within {limit} deg"
                      for limit, near in close.items()]
            lines.append(f"retrieval k={k}: {len(pairs)} of {len(all_pairs)} pairs; "
                         f"recall {', '.join(recall)}")
    if turned:
        # bench_celery_sfm's 270 images: each view also turned by 90 and 270 degrees.
        # The unturned views' descriptors are the ones above.
        everything = [turned_view for path, upright in zip(images.paths, descriptors, strict=True)
                      for turned_view in (upright, *(
                          detect_features(np.ascontiguousarray(np.rot90(load_rgb(path), turns)), config)
                          .descriptors for turns in (1, 3)))]
        threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            for cap in vocabulary_descriptors:
                start = time.perf_counter()
                train_vocabulary(everything, config.vocabulary_size, cap or sys.maxsize)
                seconds = time.perf_counter() - start
                lines.append(f"turned views ({len(everything)} images): vocabulary on {cap or 'all'} of "
                             f"{sum(map(len, everything))} descriptors in {seconds:.2f} s (k-means on one "
                             "OpenCV thread)")
        finally:
            cv2.setNumThreads(threads)
    return lines


def descriptor_caps(text: str) -> list[int]:
    """--vocabulary-descriptors: comma-separated whole numbers >= 0 (0: every descriptor)."""
    try:
        caps = [int(value) for value in text.split(",")]
    except ValueError:
        caps = []
    if not caps or min(caps) < 0:
        raise argparse.ArgumentTypeError(
            f"--vocabulary-descriptors: expected comma-separated whole numbers >= 0, got {text!r}")
    return caps


def run_ours(folder: Path, K: np.ndarray, config: SiftConfig) -> dict:
    """Seconds per stage (sift_tracks' own) and the pair statistics."""
    images = list_images(folder)
    start = time.perf_counter()
    result = sift_tracks(images, config, TwoViewConfig(), RansacConfig(), K=K)
    end = time.perf_counter()
    verified = [g.num_inliers for g in result.two_view.values() if g.num_inliers > 0]
    return {
        "images": len(images),
        "extract": result.seconds_per_stage["detection"],
        "match": result.seconds_per_stage["matching_and_verification"],   # one stage, as pycolmap's
        "verify": float("nan"),
        "total": end - start,
        "keypoints": float(np.mean(result.keypoints_per_image)),
        "pairs": len(result.matches_per_pair),
        "matches_per_pair": float(np.mean(list(result.matches_per_pair.values()))),
        "verified_pairs": len(verified),
        "inliers_per_verified_pair": float(np.mean(verified)) if verified else 0.0,
        "types": Counter(g.type.value for g in result.two_view.values() if g.num_inliers > 0),
    }


def run_pycolmap(folder: Path, K: np.ndarray, max_side: int, max_features: int, work: Path) -> dict:
    """pycolmap.extract_features + match_exhaustive on the same images with the same K (COLMAP pixels)."""
    import pycolmap

    names = list_images(folder).names
    database = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    # COLMAP puts pixel centres at +0.5: its principal point is ours + 0.5.
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_side
    extraction.sift.max_num_features = max_features
    start = time.perf_counter()
    pycolmap.extract_features(database, folder, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    extracted = time.perf_counter()
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    end = time.perf_counter()

    db = pycolmap.Database.open(database)
    _, raw = db.read_all_matches()
    _, geometries = db.read_two_view_geometries()
    keypoints = [db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()]
    db.close()
    verified = [len(g.inlier_matches) for g in geometries if len(g.inlier_matches) > 0]
    num_pairs = len(names) * (len(names) - 1) // 2
    return {
        "images": len(names),
        "extract": extracted - start,
        "match": end - extracted,          # matching and verification together
        "verify": float("nan"),
        "total": end - start,
        "keypoints": float(np.mean(keypoints)),
        "pairs": num_pairs,
        "matches_per_pair": float(sum(len(m) for m in raw) / num_pairs),
        "verified_pairs": len(verified),
        "inliers_per_verified_pair": float(np.mean(verified)) if verified else 0.0,
        "types": Counter(str(g.config).split(".")[-1].lower()
                         for g in geometries if len(g.inlier_matches) > 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", choices=["lego", "fountain"], default=["lego", "fountain"])
    parser.add_argument("--max-side", type=int, default=SiftConfig().max_image_side)
    parser.add_argument("--max-features", type=int, default=SiftConfig().max_features)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--vocabulary-descriptors", type=descriptor_caps,
                        default=[VOCABULARY_TRAINING_DESCRIPTORS],
                        help="comma-separated caps on the descriptors training lego's retrieval vocabulary "
                        "(0: all of them)")
    parser.add_argument("--turned", action="store_true",
                        help="also time that training on lego's views each turned by 90 and 270 degrees")
    args = parser.parse_args()
    config = SiftConfig(max_image_side=args.max_side, max_features=args.max_features)
    print(f"load before: {os.getloadavg()}  (cores: {os.cpu_count()})")
    rows, retrieval = [], []
    for name in args.sets:
        with tempfile.TemporaryDirectory(prefix="bench_features_") as tmp:
            work = Path(tmp)
            if name == "lego":
                folder = work / "images"
                folder.mkdir()
                K = prepare_lego(args.data, folder)
                retrieval = lego_retrieval_recall(args.data, folder, config, args.vocabulary_descriptors,
                                                  args.turned)
            else:
                folder = args.data / "strecha" / "fountain-P11"
                K = find_calibration(folder)
            ours = run_ours(folder, K, config)
            theirs = run_pycolmap(folder, K, args.max_side, args.max_features, work)
        rows.append((name, ours, theirs))

    print(f"\nmax side {args.max_side}, feature budget {args.max_features}; seconds (pycolmap's 'match' "
          "includes its verification)\n")
    print("| set | method | images | keypoints/img | extract s | match s | verify s | total s | "
          "ratio ours/pycolmap | pairs | matches/pair | verified pairs | inliers/verified pair | types |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, ours, theirs in rows:
        for method, r in (("ours", ours), ("pycolmap", theirs)):
            ratio = f"{ours['total'] / theirs['total']:.2f}" if method == "ours" else ""
            types = ", ".join(f"{k} {v}" for k, v in sorted(r["types"].items()))
            print(f"| {name} | {method} | {r['images']} | {r['keypoints']:.0f} | {r['extract']:.1f} | "
                  f"{r['match']:.1f} | {r['verify']:.1f} | {r['total']:.1f} | {ratio} | {r['pairs']} | "
                  f"{r['matches_per_pair']:.1f} | {r['verified_pairs']} | "
                  f"{r['inliers_per_verified_pair']:.1f} | {types} |")
    print("\n".join(["", *retrieval]))
    print(f"\nload after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
