"""What the machine's cores add: the same CPU-bound work in one process, then in one process per core at
once, and the speed-up that gives (the number of cores where they are independent; less where they share
a physical core or the host's time). Every figure of this project measured "on both cores" is bounded by it.

    python benchmarks/bench_cores.py
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

ENVIRONMENT = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
"""Each process computes on one thread (read by numpy's BLAS as it loads in the spawned processes)."""


def python_loop(iterations: int) -> float:
    """Seconds of a pure-Python loop (the interpreter's work: RANSAC's and the mapper's bookkeeping)."""
    start, total = time.perf_counter(), 0
    for value in range(iterations):
        total += value
    return time.perf_counter() - start


def matrix_products(iterations: int) -> float:
    """Seconds of 200 x 200 matrix products (BLAS: descriptor matching's distance products)."""
    a = np.random.default_rng(0).random((200, 200))
    start = time.perf_counter()
    for _ in range(iterations):
        a @ a
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=len(os.sched_getaffinity(0)))
    args = parser.parse_args()
    os.environ.update(ENVIRONMENT)
    for name, work, iterations in (("Python loop", python_loop, 20_000_000),
                                   ("200x200 products", matrix_products, 3000)):
        with ProcessPoolExecutor(args.processes, mp_context=multiprocessing.get_context("spawn")) as pool:
            list(pool.map(work, [1] * args.processes))        # every process started before the timing
            alone = pool.submit(work, iterations).result()
            together = list(pool.map(work, [iterations] * args.processes))
        speedup = args.processes * alone / max(together)
        print(f"{name}: {alone:.2f} s alone, {', '.join(f'{s:.2f}' for s in together)} s with "
              f"{args.processes} at once: {speedup:.2f}x the work of one process per second")


if __name__ == "__main__":
    main()
