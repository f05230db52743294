"""The initial pair's relative pose: verification's E (two_view.max_error_px, 4 px) against the E that
`mapper.initial_pair.tight_essential` estimates again on its inliers (initial_pair_max_error_px), on lego's
pairs, and the mapper end to end on small synthetic object captures.

Lego: SIFT tracks of the 90 views (composited on white, K from camera_angle_x, the default configuration);
for the --pairs image pairs sharing most tracks (the initial pair's candidates come first from them) and
each RANSAC seed, both relative rotations (chirality-checked, `choose_relative_pose`) against the ground
truth's R_j R_i^T: the median and mean error and how many exceed 5 degrees.

Synthetic (`synthetic.make_object_scene`): 30 cameras in a ring or a hemisphere around an object, 1500
points, 30 % outlier observations, scene seeds 0..--scenes-1 of each layout, at 200x150 px with 0.5 px
noise and 640x480 px with 1 px; the mapper (`reconstruct_models` with the true K) of --code (default this
checkout; e.g. a `git archive` of an earlier commit) and each model's mean rotation error after similarity
alignment: their mean, the worst model's, and the models above 5 degrees (flipped).

    python benchmarks/bench_initial_pair.py
    python benchmarks/bench_initial_pair.py --pairs 80 --seeds 0,1,2,3,4,5,6,7 --no-synthetic
    mkdir -p /tmp/base && git archive 4d86084 | tar -x -C /tmp/base
    python benchmarks/bench_initial_pair.py --no-lego --code /tmp/base
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

BENCHMARKS = Path(__file__).resolve().parent
SIZES = ((200, 150, 0.5), (640, 480, 1.0))
"""Synthetic image width, height and pixel noise."""
FLIPPED_DEG = 5.0


def lego_pairs(pairs: int, seeds: list[int]) -> None:
    from bench_sfm import lego_set

    from estimation import ReconstructionConfig
    from estimation.geometry.alignment import relative_pose, rotation_angle_deg
    from estimation.io.images import list_images
    from estimation.mapper.initial_pair import co_visible_pairs, tight_essential
    from estimation.pipeline import extract_tracks
    from estimation.two_view.essential import choose_relative_pose, essential_from_fundamental
    from estimation.two_view.geometry import estimate_two_view_geometry

    with tempfile.TemporaryDirectory() as work:
        bench = lego_set(Path(work))
        K = bench.K
        tracks = extract_tracks(list_images(bench.images), ReconstructionConfig(features="sift"), K=K).tracks
    errors: dict[str, list[float]] = {"verification (4 px)": [], "tight_essential": []}
    for i, j, _ in sorted(co_visible_pairs(tracks), key=lambda pair: -pair[2])[:pairs]:
        _, uv_i, uv_j = tracks.pair_correspondences(i, j)
        names = tracks.image_names
        truth = relative_pose(bench.truth[names[i]], bench.truth[names[j]]).R
        for seed in seeds:
            config = ReconstructionConfig(ransac={"seed": seed})
            verified = estimate_two_view_geometry(uv_i, uv_j, K, K, config.two_view, config.ransac)
            inlier_i, inlier_j = uv_i[verified.inlier_mask], uv_j[verified.inlier_mask]
            E = verified.E if verified.E is not None else essential_from_fundamental(verified.F, K)
            tight = tight_essential(K, E, inlier_i, inlier_j, config)
            for name, essential in (("verification (4 px)", E), ("tight_essential", tight)):
                pose = choose_relative_pose(essential, K, inlier_i, inlier_j).pose
                errors[name].append(rotation_angle_deg(pose.R, truth))
    print("| E of the relative pose | pairs x seeds | median deg | mean deg | above 5 deg |")
    print("|---|---|---|---|---|")
    for name, values in errors.items():
        values = np.array(values)
        print(f"| {name} | {len(values)} | {np.median(values):.2f} | {values.mean():.2f} | "
              f"{(values > 5).sum()} |")


def synthetic_models(scenes: int) -> None:
    from estimation import ReconstructionConfig
    from estimation.geometry.alignment import aligned_pose_errors
    from estimation.mapper.incremental import reconstruct_models
    from estimation.synthetic import make_object_scene

    config = ReconstructionConfig(write_figures=False)
    print("| size, noise | models | all cameras registered | mean of the mean rotation errors deg | worst "
          f"model's deg | models above {FLIPPED_DEG:g} deg |")
    print("|---|---|---|---|---|---|")
    for width, height, noise in SIZES:
        means, complete = [], 0
        for layout in ("ring", "hemisphere"):
            for seed in range(scenes):
                scene = make_object_scene(num_cameras=30, layout=layout, num_points=1500, noise_px=noise,
                                          outlier_fraction=0.3, seed=seed, width=width, height=height)
                model = reconstruct_models(scene.tracks, scene.K, config)[0]
                images = sorted(model.poses)
                complete += len(images) == 30
                truth = [scene.poses[m] for m in images]
                means.append(aligned_pose_errors([model.poses[m] for m in images], truth).rotation_deg.mean())
        means = np.array(means)
        print(f"| {width}x{height}, {noise} px | {len(means)} | {complete} | {means.mean():.3f} | "
              f"{means.max():.3f} | {(means > FLIPPED_DEG).sum()} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=40, help="lego: pairs with most shared tracks")
    parser.add_argument("--seeds", default="0,1,2,3", help="lego: comma-separated RANSAC seeds")
    parser.add_argument("--scenes", type=int, default=8, help="synthetic: scene seeds per layout")
    parser.add_argument("--no-lego", action="store_true", help="skip the lego pairs")
    parser.add_argument("--no-synthetic", action="store_true", help="skip the synthetic captures")
    parser.add_argument("--code", type=Path, default=BENCHMARKS.parent, help="the checkout whose code runs")
    args = parser.parse_args()
    sys.path.insert(0, str(args.code))
    sys.path.insert(1, str(BENCHMARKS))
    print(f"code of {args.code}")
    if not args.no_lego:
        lego_pairs(args.pairs, [int(seed) for seed in args.seeds.split(",")])
    if not args.no_synthetic:
        synthetic_models(args.scenes)


if __name__ == "__main__":
    main()
