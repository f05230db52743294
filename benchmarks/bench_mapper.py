"""The incremental mapper alone on lego's SIFT tracks: CPU and stage seconds and accuracy per RANSAC seed.

Lego's verified tracks (SIFT, exhaustive matching, verification with the known K; the 90 views composited
on white) are computed once and cached in --work as an .npz; every run then maps them with
`estimation.mapper.incremental.reconstruct_models` (default ReconstructionConfig, the seed given) and
prints the registered images, the mean and max rotation error against the ground truth after a similarity
alignment, the points, and wall and CPU seconds (`time.process_time`: little moved by other work). With
--code DIR the mapper is imported from DIR instead (another checkout, e.g. a `git archive` of an earlier
commit), so two versions can be timed on the same tracks one after the other.

    python benchmarks/bench_mapper.py --seeds 0,1,2
    mkdir -p /tmp/base && git archive 304f5ed | tar -x -C /tmp/base
    bash -c 'for s in 0 1 2; do python benchmarks/bench_mapper.py --seeds $s \\
        --code /tmp/base; python benchmarks/bench_mapper.py --seeds $s; done'
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_WORK = Path("/tmp/sfmnerf-bench-mapper")


def cached_tracks(work: Path) -> dict[str, np.ndarray]:
    """Lego's tracks, K, the two-view types of the verified pairs and the true poses, cached in `work`."""
    cache = work / "lego_tracks.npz"
    if not cache.exists():
        from bench_sfm import lego_set

        from estimation import ReconstructionConfig
        from estimation.io.images import list_images
        from estimation.pipeline import extract_tracks

        bench = lego_set(work)
        images = list_images(bench.images)
        config = ReconstructionConfig(features="sift", write_figures=False)
        features = extract_tracks(images, config, K=bench.K)
        index_of = {name: m for m, name in enumerate(images.names)}
        pairs = [(sorted(index_of[n] for n in pair.split("|")), geometry["type"])
                 for pair, geometry in features.details["two_view_geometry_per_pair"].items()]
        tracks = features.tracks
        np.savez(cache, names=np.array(tracks.image_names), track_index=tracks.track_index,
                 image_index=tracks.image_index, uv=tracks.uv, colors=tracks.colors, K=bench.K,
                 pairs=np.array([p for p, _ in pairs]), pair_types=np.array([t for _, t in pairs]),
                 true_R=np.stack([bench.truth[n].R for n in images.names]),
                 true_t=np.stack([bench.truth[n].t for n in images.names]))
    return dict(np.load(cache))


def map_once(data: dict[str, np.ndarray], seed: int) -> str:
    """One mapping of the cached tracks with RANSAC seed `seed`: a table row."""
    from estimation import ReconstructionConfig
    from estimation.geometry.alignment import aligned_pose_errors
    from estimation.mapper.incremental import reconstruct_models
    from estimation.types import CameraPose, Tracks

    tracks = Tracks([str(n) for n in data["names"]], data["track_index"], data["image_index"], data["uv"],
                    data["colors"])
    pair_types = {(int(i), int(j)): str(kind)
                  for (i, j), kind in zip(data["pairs"], data["pair_types"], strict=True)}
    config = ReconstructionConfig(features="sift", write_figures=False, ransac={"seed": seed})
    wall, cpu = time.perf_counter(), time.process_time()
    model = reconstruct_models(tracks, data["K"], config, pair_types=pair_types)[0]
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    images = sorted(model.poses)
    errors = aligned_pose_errors([model.poses[m] for m in images],
                                 [CameraPose(data["true_R"][m], data["true_t"][m]) for m in images])
    stages = ", ".join(f"{stage} {seconds:.2f}" for stage, seconds in model.stats.stage_seconds.items())
    return (f"| {seed} | {len(images)}/{len(tracks.image_names)} | {errors.rotation_deg.mean():.3f} | "
            f"{errors.rotation_deg.max():.3f} | {len(model.points)} | {wall:.2f} | {cpu:.2f} | {stages} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0", help="comma-separated RANSAC seeds, a row each")
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK, help="where the cached tracks go")
    parser.add_argument("--code", type=Path, default=ROOT, help="the checkout whose mapper runs")
    args = parser.parse_args()
    sys.path.insert(0, str(args.code))
    sys.path.insert(1, str(ROOT / "benchmarks"))
    args.work.mkdir(parents=True, exist_ok=True)
    data = cached_tracks(args.work)
    print(f"mapper of {args.code}")
    print("| seed | registered | rot mean deg | rot max deg | points | wall s | CPU s | seconds per stage |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        print(map_once(data, seed), flush=True)


if __name__ == "__main__":
    main()
