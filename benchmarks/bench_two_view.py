"""Geometric verification alone on lego: CPU seconds of `estimate_two_view_geometry` over the pairs that
`sift_tracks` verifies, in one process, and its decisions compared with a saved run.

The matches are computed once (SIFT, exhaustive pairs, matching as in `sift_tracks`) and cached in --work;
each repeat then verifies every pair with at least min_inliers matches, without the polish of E (as
`sift_tracks` does), timed by time.process_time: CPU seconds, which other processes barely move. --save
writes every pair's type, inlier mask and (F, E, H) inlier counts; --compare counts the pairs whose type,
inlier mask or counts differ from such a file (written, for instance, on main).

    python benchmarks/bench_two_view.py --save /tmp/two_view_main.npz        # on main
    python benchmarks/bench_two_view.py --compare /tmp/two_view_main.npz     # on a branch
    python benchmarks/bench_two_view.py --compare /tmp/two_view_main.npz --seed 1   # sampling noise
    python benchmarks/bench_two_view.py --repeat 1 --profile 25              # cProfile's top 25
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_features import DATA, prepare_lego  # noqa: E402

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig  # noqa: E402
from estimation.two_view.geometry import TwoViewGeometry, estimate_two_view_geometry  # noqa: E402


def verification_inputs(work: Path) -> dict[str, np.ndarray]:
    """K and, per verifiable pair of lego (at least min_inliers matches), the matched uv1, uv2: cached."""
    cache = work / "lego_verification_inputs.npz"
    if not cache.exists():
        from estimation.features.pairs import candidate_pairs
        from estimation.features.sift import PairWork, detect_features, match_and_verify_pairs
        from estimation.io.images import list_images, load_rgb
        from estimation.parallel import WorkerPool

        folder = work / "lego"
        folder.mkdir(parents=True, exist_ok=True)
        K = prepare_lego(DATA, folder)
        config = SiftConfig(device="cpu")
        images = list_images(folder)
        features = [detect_features(load_rgb(path), config) for path in images.paths]
        pairs = candidate_pairs(images.names, [f.descriptors for f in features], config)
        matches, _ = match_and_verify_pairs(PairWork.of(features, config), pairs, WorkerPool(1))
        verifiable = [pair for pair in pairs if len(matches[pair].ratio) >= TwoViewConfig().min_inliers]
        uv1 = [features[i].uv[matches[(i, j)].index_a] for i, j in verifiable]
        uv2 = [features[j].uv[matches[(i, j)].index_b] for i, j in verifiable]
        np.savez(cache, K=K, pairs=np.array(verifiable), offsets=np.cumsum([0] + [len(uv) for uv in uv1]),
                 uv1=np.concatenate(uv1), uv2=np.concatenate(uv2))
    return dict(np.load(cache))


def verify_all(inputs: dict[str, np.ndarray], seed: int) -> list[TwoViewGeometry]:
    """`estimate_two_view_geometry` of every cached pair with the default configuration (but the RANSAC
    seed), in order."""
    K, offsets = inputs["K"], inputs["offsets"]
    return [estimate_two_view_geometry(inputs["uv1"][start:end], inputs["uv2"][start:end], K, K,
                                       TwoViewConfig(), RansacConfig(seed=seed), refine_essential=False)
            for start, end in zip(offsets[:-1], offsets[1:], strict=True)]


def decisions(results: list[TwoViewGeometry]) -> dict[str, np.ndarray]:
    """Every pair's type, inlier counts (F, E, H) and inlier mask (concatenated), as arrays."""
    return {"types": np.array([str(r.type) for r in results]),
            "counts": np.array([(r.num_inliers_f, r.num_inliers_e, r.num_inliers_h) for r in results]),
            "masks": np.concatenate([r.inlier_mask for r in results])}


def differences(saved: dict[str, np.ndarray], now: dict[str, np.ndarray], offsets: np.ndarray) -> list[str]:
    """Lines counting the pairs whose type, inlier mask or inlier counts differ, and the type changes."""
    changed_rows = saved["masks"] != now["masks"]
    mask_changes = np.add.reduceat(changed_rows, offsets[:-1]) > 0 if len(changed_rows) else np.zeros(0)
    type_changes = Counter(f"{a} -> {b}" for a, b in zip(saved["types"], now["types"], strict=True) if a != b)
    count_changes = (saved["counts"] != now["counts"]).any(axis=1)
    return [f"pairs with another type: {sum(type_changes.values())} {dict(type_changes)}",
            f"pairs with another inlier mask: {int(mask_changes.sum())} ({int(changed_rows.sum())} rows)",
            f"pairs with other (F, E, H) inlier counts: {int(count_changes.sum())}"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("/tmp/sfmnerf-bench-two-view"),
                        help="where lego's images and the cached matches go")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs (the minimum is reported)")
    parser.add_argument("--save", type=Path, help="write the decisions (.npz) here")
    parser.add_argument("--compare", type=Path, help="count the differences from decisions saved here")
    parser.add_argument("--seed", type=int, default=RansacConfig().seed,
                        help="RANSAC seed: another seed's differences are the sampling's own noise")
    parser.add_argument("--profile", type=int, default=0, help="print cProfile's top N functions of one run")
    args = parser.parse_args()

    inputs = verification_inputs(args.work)
    if args.profile:
        profile = cProfile.Profile()
        profile.runcall(verify_all, inputs, args.seed)
        pstats.Stats(profile).sort_stats("tottime").print_stats(args.profile)
    seconds = []
    for _ in range(args.repeat):
        started = time.process_time()
        results = verify_all(inputs, args.seed)
        seconds.append(time.process_time() - started)
    print(f"{len(results)} pairs verified; CPU s per run: {' '.join(f'{s:.2f}' for s in seconds)} "
          f"(min {min(seconds):.2f})")
    print("types:", dict(Counter(str(r.type) for r in results)))
    now = decisions(results)
    if args.save:
        np.savez(args.save, **now)
    if args.compare:
        print("\n".join(differences(dict(np.load(args.compare)), now, inputs["offsets"])))


if __name__ == "__main__":
    main()
