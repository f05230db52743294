"""Worker processes for CPU-bound work that splits into independent items (two-view verification of
image pairs), and the worker count.

Processes, not threads: one pair's RANSAC is thousands of small numpy calls that hold the GIL. They are
started with the "spawn" context, never by fork: the parent may already run torch's or OpenCV's threads
(and the service's job processes do). Every process dies with the process that started it, so a killed
job leaves none behind, and imports the modules it needs as soon as it starts, while the parent still
works on the steps before.
"""

from __future__ import annotations

import ctypes
import importlib
import multiprocessing
import os
import signal
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

PR_SET_PDEATHSIG = 1
PARENT_POLL_SECONDS = 1.0
CHUNKS_PER_WORKER = 8
"""Items are sent to the processes in this many chunks per process: few round trips, and a slow chunk
at the end still leaves the others busy."""


def available_cores() -> int:
    """CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def resolve_workers(workers: int) -> int:
    """The configured worker count; 0 means one per available core."""
    return workers if workers > 0 else available_cores()


def die_with_parent(parent_pid: int) -> None:
    """Ends this process as soon as the process that started it is gone."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(PARENT_POLL_SECONDS)

    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)
    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


def _initialize_worker(parent_pid: int, modules: tuple[str, ...]) -> None:
    die_with_parent(parent_pid)
    for module in modules:
        importlib.import_module(module)


@contextmanager
def _main_module_hidden() -> Iterator[None]:
    """Spawned processes do not re-run the caller's main script (a script without the
    `if __name__ == "__main__"` guard would run again in every process): the functions they run live
    in importable modules, so the script is hidden from multiprocessing while the processes start."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


class WorkerPool:
    """`map` over items in `workers` spawned processes, or in the calling process when there is one worker
    (or when this process may not have children: a daemonic multiprocessing worker)."""

    def __init__(self, workers: int, modules: tuple[str, ...] = ()) -> None:
        self.workers = workers if not multiprocessing.current_process().daemon else 1
        self._executor: ProcessPoolExecutor | None = None
        if self.workers > 1:
            self._executor = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_initialize_worker, initargs=(os.getpid(), modules),
            )
            with _main_module_hidden():
                for _ in range(self.workers):      # start every process now, not at the first map
                    self._executor.submit(os.getpid)

    def map(self, function: Callable[..., Any], *sequences: Sequence[Any]) -> Iterator[Any]:
        """function(*args) for args in zip(*sequences), in order, each as soon as it and those before are
        done."""
        if self._executor is None:
            return map(function, *sequences)
        chunk = max(1, min(map(len, sequences)) // (CHUNKS_PER_WORKER * self.workers))
        return self._executor.map(function, *sequences, chunksize=chunk)

    def shutdown(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)


@contextmanager
def worker_pool(workers: int, modules: tuple[str, ...] = ()) -> Iterator[WorkerPool]:
    """A WorkerPool of `workers` processes (see `resolve_workers`) importing `modules`, shut down after."""
    pool = WorkerPool(workers, modules)
    try:
        yield pool
    finally:
        pool.shutdown()
