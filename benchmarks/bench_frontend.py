"""The SIFT front end alone on lego: wall and CPU seconds of `sift_tracks` as a reconstruction calls it.

Lego's 90 views are composited on white into --work once (`bench_sfm.lego_set`); every run then calls
`estimation.features.sift.sift_tracks` with the default `ReconstructionConfig` and the known K, and prints its
wall seconds (detection, matching and verification, track building), its stages' seconds, the CPU seconds of
this process and of its finished worker processes (`RUSAGE_CHILDREN`), and the CPU seconds the machine spent
on other processes meanwhile (from /proc/stat: a run where they are not near 0 shared the cores). With
--timeline, the busy cores every 50 ms (from /proc/stat). With --code DIR the front end is imported from DIR
(another checkout, e.g. a `git archive` of an earlier commit). --save writes the result (keypoint counts,
matches and inliers per pair, two-view geometries, tracks) and --compare checks it bitwise against a saved
one.

    python benchmarks/bench_frontend.py --timeline
    mkdir -p /tmp/base && git archive ca7ff17 | tar -x -C /tmp/base
    bash -c 'for k in 1 2 3; do python benchmarks/bench_frontend.py --code \\
        /tmp/base --save /tmp/base.pkl; python benchmarks/bench_frontend.py --compare /tmp/base.pkl; done'
"""

from __future__ import annotations

import argparse
import os
import pickle
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_WORK = Path("/tmp/sfmnerf-bench-frontend")
SAMPLE_SECONDS = 0.05
"""Interval of the --timeline samples of /proc/stat."""


def lego_folder(work: Path) -> Path:
    """Lego's images and calibration.txt in `work`, made the first time by `bench_sfm.lego_set` in another
    process (importing bench_sfm puts this checkout first on sys.path, where --code must come first)."""
    folder = work / "lego"
    if not (folder / "calibration.txt").exists():
        make = f"from pathlib import Path; from bench_sfm import lego_set; lego_set(Path({str(work)!r}))"
        subprocess.run([sys.executable, "-c", make], cwd=ROOT / "benchmarks", check=True)
    return folder


def cpu_ticks() -> tuple[int, int]:
    """The machine's busy and total CPU ticks since boot (/proc/stat's first line)."""
    with open("/proc/stat") as stat:
        ticks = [int(value) for value in stat.readline().split()[1:]]
    idle = ticks[3] + ticks[4]          # idle, iowait
    return sum(ticks) - idle, sum(ticks)


def own_cpu_seconds() -> tuple[float, float]:
    """CPU seconds of this process and of its finished children."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time(), children.ru_utime + children.ru_stime


class Timeline:
    """Busy cores sampled every SAMPLE_SECONDS in a thread, as (seconds since start, cores busy)."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._start = time.perf_counter()
        self._thread.start()

    def _sample(self) -> None:
        cores = os.cpu_count() or 1
        before = cpu_ticks()
        while not self._stop.wait(SAMPLE_SECONDS):
            after = cpu_ticks()
            busy = cores * (after[0] - before[0]) / max(1, after[1] - before[1])
            self.samples.append((time.perf_counter() - self._start, busy))
            before = after

    def stop(self) -> str:
        """The samples as 'seconds:cores' words."""
        self._stop.set()
        self._thread.join()
        return " ".join(f"{at:.2f}:{busy:.1f}" for at, busy in self.samples)


def result_arrays(result) -> dict:
    """What `sift_tracks` found, as plain values and arrays (for --save and --compare)."""
    tracks = result.tracks
    return {
        "keypoints_per_image": result.keypoints_per_image,
        "matches_per_pair": result.matches_per_pair,
        "verified_per_pair": result.verified_per_pair,
        "num_rejected_links": result.num_rejected_links,
        "two_view": {pair: (geometry.type.value, geometry.inlier_mask, geometry.E, geometry.F, geometry.H)
                     for pair, geometry in result.two_view.items()},
        "tracks": (tracks.track_index, tracks.image_index, tracks.uv, tracks.colors),
    }


def bitwise_equal(a, b) -> bool:
    """Equal values, and arrays of the same dtype, shape and bytes."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(bitwise_equal(a[key], b[key]) for key in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(bitwise_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    return a == b


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK, help="where lego's images are made once")
    parser.add_argument("--code", type=Path, default=ROOT, help="the checkout whose front end runs")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--timeline", action="store_true", help="print the busy cores every 50 ms")
    parser.add_argument("--save", type=Path, help="write the last run's result here (pickle)")
    parser.add_argument("--compare", type=Path, help="check the result bitwise against this saved one")
    parser.add_argument("--defer-planarity", action="store_true",
                        help="leave the pairs' planarity tests (H) out, as `reconstruct` does (they run "
                        "beside its mapper)")
    args = parser.parse_args()
    folder = lego_folder(args.work)
    sys.path.insert(0, str(args.code))          # the worker processes inherit it
    import estimation
    from estimation.config import ReconstructionConfig
    from estimation.features.sift import sift_tracks
    from estimation.io.images import list_images

    images, K = list_images(folder), np.loadtxt(folder / "calibration.txt")
    config = ReconstructionConfig()
    print(f"front end of {Path(estimation.__file__).parents[1]}; load {os.getloadavg()[0]:.2f}")
    for _ in range(args.repeats):
        timeline = Timeline() if args.timeline else None
        ticks, (cpu, children) = cpu_ticks(), own_cpu_seconds()
        start = time.perf_counter()
        planarity = {"defer_planarity": True} if args.defer_planarity else {}
        result = sift_tracks(images, config.sift, two_view=config.two_view, ransac=config.ransac, K=K,
                             **planarity)
        wall = time.perf_counter() - start
        after_cpu, after_children = own_cpu_seconds()
        busy = (cpu_ticks()[0] - ticks[0]) / os.sysconf("SC_CLK_TCK")
        here, workers = after_cpu - cpu, after_children - children
        stages = ", ".join(f"{stage} {seconds:.3f}" for stage, seconds in result.seconds_per_stage.items())
        print(f"{wall:.3f} s ({stages}); CPU s {here:.2f} here + {workers:.2f} in the worker processes; "
              f"other processes {busy - here - workers:+.2f} CPU s; load {os.getloadavg()[0]:.2f}",
              flush=True)
        if timeline is not None:
            print("busy cores:", timeline.stop())
    if args.save:
        args.save.write_bytes(pickle.dumps(result_arrays(result)))
    if args.compare:
        same = bitwise_equal(result_arrays(result), pickle.loads(args.compare.read_bytes()))
        print(f"bitwise equal to {args.compare}: {same}")


if __name__ == "__main__":
    main()
