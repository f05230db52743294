"""A reconstruction's feature extraction and matching spread over Celery workers: seconds with 1 and with 2
workers (or --workers) on 200+ images, and the ratio.

The images: lego_200's 90 views (train and val), each also turned by 90 and by 270 degrees (270 images of
200x200; the turned copies are other images to SIFT, and match their originals like close views do),
numbered in that order. This process plays the job's own Celery worker (`service.spread.CeleryStages`:
it sends the tasks and computes chunks itself, from the last), and N - 1 Celery worker processes
(prefork, concurrency 1, on a redis-server started here) take the others; `sift_tracks` runs as a
reconstruction calls it (the known K, planarity tests deferred). Every run must find the same keypoints and
verified matches. With --repeats, the worker counts take turns and the fastest run of each is compared.

    python benchmarks/bench_celery_sfm.py [--views 90] [--workers 1 2] [--images-per-chunk 8]
        [--pairs-per-block 300] [--repeats 1] [--cores-per-worker 1]

Each worker is pinned to cores of its own (`--cores-per-worker`, 1 by default), as workers on machines of
their own would be: unpinned, one worker's OpenCV threads already use every core of this machine, and the
second worker only competes for them. On a machine shared with other work the ratio of wall times says
less than on idle cores; each run also prints the CPU seconds the busiest worker process spent on chunks
against those of all (the share of the work on the longest path, whatever the load).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the tests' server helpers

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig  # noqa: E402
from estimation.features.sift import sift_tracks  # noqa: E402
from estimation.io.images import list_images  # noqa: E402
from estimation.parallel import blas_threads  # noqa: E402
from service.layout import input_dir  # noqa: E402
from service.spread import CeleryStages  # noqa: E402
from tests.service.conftest import make_settings  # noqa: E402
from tests.service.servers import start_redis  # noqa: E402
from tests.service.test_celery import start_worker, stop_worker, worker_env  # noqa: E402
from tests.service.test_spread import wait_until_every_worker_works  # noqa: E402

LEGO = ROOT.parent / "shared" / "data" / "lego_200"
TURNS = (0, 1, 3)
"""Quarter turns of each view: 90 views make 270 images."""
JOB_ID = "bench"


def write_images(folder: Path, views: int) -> tuple[list[Path], np.ndarray]:
    """The first `views` lego views, turned, as numbered PNGs in `folder`, and their K (square images:
    turning keeps it)."""
    folder.mkdir(parents=True)
    paths, angle = [], None
    for split in ("train", "val"):
        frames = json.loads((LEGO / f"transforms_{split}.json").read_text())
        angle = frames["camera_angle_x"]
        paths += [LEGO / f"{frame['file_path']}.png" for frame in frames["frames"]]
    written = []
    for view in paths[:views]:
        image = cv2.imread(str(view), cv2.IMREAD_UNCHANGED)
        for turns in TURNS:
            written.append(folder / f"img_{len(written):04d}.png")
            cv2.imwrite(str(written[-1]), np.ascontiguousarray(np.rot90(image, turns)))
    side = image.shape[0]
    focal = 0.5 * side / math.tan(0.5 * angle)
    return written, np.array([[focal, 0, (side - 1) / 2], [0, focal, (side - 1) / 2], [0, 0, 1]])


def worker_cores(workers: int, cores_per_worker: int) -> list[set[int]]:
    """The cores each worker is pinned to (this process first), `cores_per_worker` each, none shared."""
    cores = sorted(os.sched_getaffinity(0))
    if workers * cores_per_worker > len(cores):
        raise SystemExit(f"{workers} workers of {cores_per_worker} core(s) need {workers * cores_per_worker} "
                         f"cores; this process may use {len(cores)}")
    return [set(cores[number * cores_per_worker:(number + 1) * cores_per_worker])
            for number in range(workers)]


def pin(cores: set[int]) -> None:
    """Pins every thread of this process (OpenCV's pool included) to `cores`, with a thread per core for
    OpenCV; threads and processes started later inherit the cores (a process importing OpenCV then sizes
    its pool to them)."""
    for thread in os.listdir("/proc/self/task"):  # sched_setaffinity(0) would pin the calling thread only
        os.sched_setaffinity(int(thread), cores)
    cv2.setNumThreads(len(cores))  # more threads than cores wait on each other


def run(settings, workers: int, K: np.ndarray, cores_per_worker: int) -> tuple[float, dict, object]:
    """Seconds of extraction and matching with `workers` workers (this process and workers - 1 Celery
    workers, each on cores of its own), the seconds per stage, and the result."""
    queues = [f"bench-{workers}-{number}" for number in range(workers - 1)]
    all_cores = os.sched_getaffinity(0)
    own_cores, *celery_cores = worker_cores(workers, cores_per_worker)
    celery_workers = []
    for queue, cores in zip(queues, celery_cores, strict=True):
        pin(cores)  # the worker and its pool's processes inherit the cores
        celery_workers.append(start_worker(worker_env(settings), queues=f"celery,{queue}"))
    pin(own_cores)
    try:
        if queues:
            wait_until_every_worker_works(settings, queues, LEGO / "train" / "r_0.png")
        images = list_images(input_dir(settings, JOB_ID))
        stages = CeleryStages(settings, JOB_ID, workers, log=lambda line: print("   ", line))
        started = time.perf_counter()
        try:
            with blas_threads(len(own_cores)):  # numpy's BLAS started a thread per core of the machine
                result = sift_tracks(images, SiftConfig(workers=1), TwoViewConfig(), RansacConfig(), K=K,
                                     defer_planarity=True, stages=stages)
        finally:
            stages.close()
        busiest = sum(max(seconds) for seconds in stages.cpu_seconds.values())
        print(f"    CPU seconds of the busiest process / of all: {busiest:.1f} / "
              f"{sum(map(sum, stages.cpu_seconds.values())):.1f}")
        return time.perf_counter() - started, result.seconds_per_stage, result
    finally:
        pin(all_cores)
        for worker in celery_workers:
            stop_worker(worker)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--views", type=int, default=90, help="lego views used (3 images each)")
    parser.add_argument("--images-per-chunk", type=int, default=8)
    parser.add_argument("--pairs-per-block", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs of each worker count, interleaved; the fastest of each is compared")
    parser.add_argument("--cores-per-worker", type=int, default=1,
                        help="cores each worker is pinned to, none shared")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as temporary:
        folder = Path(temporary)
        redis_server, broker_url = start_redis(folder)
        try:
            seconds: dict[int, float] = {}
            reference = None
            for repeat, workers in itertools.product(range(args.repeats), args.workers):
                # A data folder and a broker database per run: no message of one run reaches the next.
                run_number = repeat * len(args.workers) + args.workers.index(workers)
                settings = make_settings(folder / f"data-{run_number}", executor="celery",
                                         broker_url=f"{broker_url.rsplit('/', 1)[0]}/{run_number + 1}",
                                         spread_images_per_chunk=args.images_per_chunk,
                                         spread_pairs_per_block=args.pairs_per_block)
                paths, K = write_images(input_dir(settings, JOB_ID), args.views)
                print(f"{workers} worker(s), {len(paths)} images:")
                wall, stages, result = run(settings, workers, K, args.cores_per_worker)
                seconds[workers] = min(wall, seconds.get(workers, math.inf))
                print(f"  {wall:.1f} s (detection {stages['detection']:.1f} s, matching and "
                      f"verification {stages['matching_and_verification']:.1f} s), "
                      f"{sum(result.verified_per_pair.values())} verified matches in "
                      f"{len(result.verified_per_pair)} pairs")
                found = (result.keypoints_per_image, result.verified_per_pair)
                assert reference is None or found == reference, "another run found other features"
                reference = found
        finally:
            redis_server.terminate()
            redis_server.wait(timeout=10)
    first = args.workers[0]
    for workers in args.workers[1:]:
        print(f"{workers} workers / {first}: {seconds[workers] / seconds[first]:.2f} x the time "
              f"(fastest runs: {seconds[workers]:.1f} s / {seconds[first]:.1f} s)")


if __name__ == "__main__":
    main()
