"""The initial pair's relative pose on lego: verification's E (two_view.max_error_px, 4 px) against the E
that `mapper.initial_pair.tight_essential` estimates again on its inliers (initial_pair_max_error_px).

Lego's SIFT tracks (90 views composited on white, K from camera_angle_x, the default configuration); for
the --pairs image pairs sharing most tracks (the initial pair's candidates come first from them) and each
RANSAC seed, both relative rotations (chirality-checked, `choose_relative_pose`) against the ground truth's
R_j R_i^T: the median and mean error and how many exceed 5 degrees.

    python benchmarks/bench_initial_pair.py
    python benchmarks/bench_initial_pair.py --pairs 80 --seeds 0,1,2,3,4,5,6,7
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sfm import lego_set  # noqa: E402

from estimation import ReconstructionConfig  # noqa: E402
from estimation.api import extract_tracks  # noqa: E402
from estimation.geometry.alignment import relative_pose, rotation_angle_deg  # noqa: E402
from estimation.io.images import list_images  # noqa: E402
from estimation.mapper.initial_pair import co_visible_pairs, tight_essential  # noqa: E402
from estimation.two_view.essential import (  # noqa: E402
    choose_relative_pose,
    essential_from_fundamental,
)
from estimation.two_view.geometry import estimate_two_view_geometry  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=40, help="pairs with most shared tracks")
    parser.add_argument("--seeds", default="0,1,2,3", help="comma-separated RANSAC seeds")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as work:
        bench = lego_set(Path(work))
        K = bench.K
        tracks = extract_tracks(list_images(bench.images), ReconstructionConfig(features="sift"), K=K).tracks
    errors: dict[str, list[float]] = {"verification (4 px)": [], "tight_essential": []}
    for i, j, _ in sorted(co_visible_pairs(tracks), key=lambda pair: -pair[2])[: args.pairs]:
        _, uv_i, uv_j = tracks.pair_correspondences(i, j)
        names = tracks.image_names
        truth = relative_pose(bench.truth[names[i]], bench.truth[names[j]]).R
        for seed in (int(s) for s in args.seeds.split(",")):
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


if __name__ == "__main__":
    main()
