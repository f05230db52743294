"""Descriptor matching alone: CPU and wall seconds of matching every pair of one image set's SIFT
descriptors, as `sift_tracks` does without verification (`match_and_verify_pairs`).

The descriptors (`detect_features` with the default `SiftConfig`) and pairs (`candidate_pairs`) are made once;
then the matching runs `--repeats` times for each `--workers` count (1: in this process; more: that many
spawned processes, started, fed the descriptors and shut down within each run; in a reconstruction they start
earlier, while the images are detected; the seconds the pool takes to start are printed once per count). CPU
seconds (`time.process_time` of this process plus its finished children's `RUSAGE_CHILDREN`) move little when
other work shares the machine; wall seconds only mean something on an otherwise idle
machine. Without a folder, the 90 lego views (../shared/data/lego_200) are composited on white into a
temporary folder first.

    python benchmarks/bench_matching.py
    python benchmarks/bench_matching.py /tmp/prof/lego_work/lego --workers 1 --repeats 5
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimation.config import SiftConfig  # noqa: E402
from estimation.features.pairs import candidate_pairs  # noqa: E402
from estimation.features.sift import (  # noqa: E402
    WORKER_MODULES,
    PairWork,
    detect_features,
    match_and_verify_pairs,
)
from estimation.io.images import list_images, load_rgb  # noqa: E402
from estimation.parallel import WorkerPool  # noqa: E402


def time_matching(folder: Path, workers: list[int], repeats: int) -> None:
    config = SiftConfig()
    images = list_images(folder)
    features = [detect_features(load_rgb(path), config) for path in images.paths]
    pairs = candidate_pairs(images.names, [f.descriptors for f in features], config)
    print(f"{folder}: {len(images.paths)} images, {sum(len(f.uv) for f in features)} keypoints, "
          f"{len(pairs)} pairs")
    work = PairWork.of(features, config)
    for count in workers:
        if count > 1:
            # The processes spawned and fed the context (a reconstruction starts them while it detects,
            # then shares the context: parallel.WorkerPool).
            wall = time.perf_counter()
            with WorkerPool(count, modules=WORKER_MODULES, context=work):
                print(f"workers {count}: the pool started in {time.perf_counter() - wall:.3f} s", flush=True)
        for _ in range(repeats):
            children = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu, wall = time.process_time(), time.perf_counter()
            with WorkerPool(count, modules=WORKER_MODULES) as pool:
                matches, _ = match_and_verify_pairs(work, pairs, pool)
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            child_cpu = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
            total = sum(len(m.ratio) for m in matches.values())
            print(f"workers {count}: {cpu + child_cpu:.3f} CPU s ({cpu:.3f} here, {child_cpu:.3f} in the "
                  f"processes), {wall:.3f} s wall, {total} matches", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, nargs="?", help="images (default: lego, made on the fly)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="processes (1: this one)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.folder is not None:
        time_matching(args.folder, args.workers, args.repeats)
        return
    from benchmarks.bench_features import DATA, prepare_lego

    with tempfile.TemporaryDirectory() as work:
        prepare_lego(DATA, Path(work))
        time_matching(Path(work), args.workers, args.repeats)


if __name__ == "__main__":
    main()
