"""Worker processes for CPU-bound work that splits into independent items (matching and verifying the
pairs of one query image), and the worker count.

Processes, not threads: one pair's RANSAC is thousands of small numpy calls that hold the GIL. They are
started with the "spawn" context, never by fork: the parent may already run torch's or OpenCV's threads
(and the service's job processes do). Every process dies with the process that started it, so a killed
job leaves none behind, and imports the modules it needs as soon as it starts. Data every item needs (the
images' descriptors) is a pool's `context`, sent to each process once (`WorkerPool.share`); it may come after
the start, so that the processes start while the caller computes it. Each process runs its BLAS on one
thread, the calling process too while it does a one-worker pool's items: the pool's processes are the
parallelism, and a BLAS thread per core in each would oversubscribe the cores. With `caller_works`, the
calling process is one of the workers (one process fewer to start, where it would only wait for the others):
the processes take the items from the front and the caller from the back, each item claimed once.
"""

from __future__ import annotations

import ctypes
import functools
import importlib
import multiprocessing
import os
import signal
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing.synchronize import Barrier
from typing import Any

PR_SET_PDEATHSIG = 1
PARENT_POLL_SECONDS = 1.0
CHUNKS_PER_WORKER = 8
"""Items are sent to the processes in this many chunks per process: few round trips, and a slow chunk
at the end still leaves the others busy."""
START_TIMEOUT_SECONDS = 120.0
"""A process waits this long for the others to start, or to receive the context; then the pool is broken (an
error, not a hang)."""
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Read by OpenBLAS, OpenMP and MKL when they load (numpy's BLAS cannot be limited after), so they are set
in the environment the processes inherit."""
OPENBLAS_THREAD_FUNCTIONS = (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                             ("openblas_get_num_threads", "openblas_set_num_threads"))
"""OpenBLAS's thread-count getter and setter as numpy's wheels (scipy-openblas, 64-bit integers) and a
plain OpenBLAS export them."""
_context: Any = None
"""The pool's context, in a worker process."""
_all_received: Barrier | None = None
"""Passed by every process of the pool once it holds a newly shared context, in a worker process."""
_claims: Any = None
"""The pool's shared (next item a process may take, first item the calling process took), in a worker
process of a pool whose caller works too."""


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


def _initialize_worker(parent_pid: int, modules: tuple[str, ...], all_started: Barrier,
                       all_received: Barrier, claims: Any) -> None:
    global _all_received, _claims
    die_with_parent(parent_pid)
    for module in modules:
        importlib.import_module(module)
    _all_received = all_received
    _claims = claims
    # No process takes an item before all are spawned: ProcessPoolExecutor spawns one at a submit only
    # while none is idle, so a process done with its first item would leave the next one to be spawned
    # later, outside `_main_module_hidden` and the one-BLAS-thread environment (seen under load, when the
    # processes read a large context as they started: the first one could finish its item).
    all_started.wait(timeout=START_TIMEOUT_SECONDS)


def _receive_context(context: Any) -> None:
    """Keeps `context` for the items to come, once every process holds it: a process waiting here takes no
    other item, so each of the pool's processes takes exactly one of the `workers` copies sent."""
    global _context
    _context = context
    _all_received.wait(timeout=START_TIMEOUT_SECONDS)


def _call_with_context(function: Callable[..., Any], *args: Any) -> Any:
    return function(_context, *args)


class _Taken:
    """A process's answer for an item the calling process took first."""


def _claimed_call(function: Callable[..., Any], index: int, *args: Any) -> Any:
    """function(*args) unless the calling process already took item `index` (then a _Taken)."""
    with _claims.get_lock():
        if index >= _claims[1]:
            return _Taken()
        _claims[0] = max(_claims[0], index + 1)
    return function(*args)


@functools.cache
def _openblas_thread_functions() -> list[tuple[Callable[[], int], Callable[[int], None]]]:
    """(get, set) of the thread count of every OpenBLAS this process has loaded, numpy's included (found in
    /proc/self/maps; none elsewhere)."""
    import numpy  # noqa: F401  (loads its OpenBLAS)

    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.rsplit("/", 1)[-1]})
    except OSError:
        return []
    functions = []
    for path in paths:
        library = ctypes.CDLL(path)
        for get, set_ in OPENBLAS_THREAD_FUNCTIONS:
            if hasattr(library, get) and hasattr(library, set_):
                functions.append((getattr(library, get), getattr(library, set_)))
                break
    return functions


@contextmanager
def blas_threads(count: int) -> Iterator[None]:
    """OpenBLAS on `count` threads inside the block, restored after: numpy loaded it with one thread per
    core, and between its calls those threads spin, burning the other cores' time."""
    functions = _openblas_thread_functions()
    before = [get() for get, _ in functions]
    for _, set_ in functions:
        set_(count)
    try:
        yield
    finally:
        for (_, set_), threads in zip(functions, before, strict=True):
            set_(threads)


def _in_one_blas_thread(function: Callable[..., Any], *args: Any) -> Any:
    with blas_threads(1):
        return function(*args)


@contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """os.environ with `values` set inside the block (processes started there inherit them), restored
    after."""
    before = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name)
            else:
                os.environ[name] = value


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
    """`map` over items in `workers` spawned processes (`caller_works`: `workers` - 1 and the calling
    process), or in the calling process when there is one worker (or when this process may not have children:
    a daemonic multiprocessing worker). With a `context` (given here or `share`d later), every call gets it
    as its first argument. As a context manager, it is shut down after the block."""

    def __init__(self, workers: int, modules: tuple[str, ...] = (), context: Any = None,
                 caller_works: bool = False) -> None:
        self.workers = workers if not multiprocessing.current_process().daemon else 1
        # The calling process as one of the workers: one process fewer to start (its interpreter and
        # imports) where the caller would only wait for the others.
        self.caller_works = caller_works and self.workers > 1
        self.processes = self.workers - 1 if self.caller_works else self.workers
        self.context: Any = None
        self._executor: ProcessPoolExecutor | None = None
        if self.workers > 1:
            spawn = multiprocessing.get_context("spawn")
            self._claims = spawn.Array("q", 2) if self.caller_works else None
            self._executor = ProcessPoolExecutor(
                self.processes, mp_context=spawn, initializer=_initialize_worker,
                initargs=(os.getpid(), modules, spawn.Barrier(self.processes), spawn.Barrier(self.processes),
                          self._claims),
            )
            with _main_module_hidden(), _environment(dict.fromkeys(BLAS_THREAD_VARIABLES, "1")):
                for _ in range(self.processes):      # start every process now, not at the first map
                    self._executor.submit(os.getpid)
        if context is not None:
            self.share(context)

    def share(self, context: Any) -> None:
        """Makes `context` the first argument of every later call, in each process (sent once to each, after
        its start: it is unpickled after the modules' imports, and the processes start side by side)."""
        self.context = context
        if self._executor is not None:
            received = [self._executor.submit(_receive_context, context) for _ in range(self.processes)]
            for future in received:
                future.result()

    def map(self, function: Callable[..., Any], *sequences: Sequence[Any]) -> Iterator[Any]:
        """function(*args), or function(context, *args), for args in zip(*sequences), in order, each as soon
        as it and those before are done."""
        if self._executor is None:
            return map(functools.partial(_in_one_blas_thread, self._here(function)), *sequences)
        if self.caller_works:
            return self._map_with_caller(function, list(zip(*sequences, strict=True)))
        chunk = max(1, min(map(len, sequences)) // (CHUNKS_PER_WORKER * self.workers))
        return self._executor.map(self._in_processes(function), *sequences, chunksize=chunk)

    def submit(self, function: Callable[..., Any], *args: Any) -> Future:
        """function(*args) (without the context) in one of the processes, without waiting for it: work beside
        the caller's own, which `result()` collects; done at once in this process where the pool has no
        processes."""
        if self._executor is not None:
            return self._executor.submit(function, *args)
        future: Future = Future()
        try:
            future.set_result(_in_one_blas_thread(function, *args))
        except Exception as error:
            future.set_exception(error)
        return future

    def _here(self, function: Callable[..., Any]) -> Callable[..., Any]:
        """`function` as this process calls it: with the context first, if there is one."""
        return functools.partial(function, self.context) if self.context is not None else function

    def _in_processes(self, function: Callable[..., Any]) -> Callable[..., Any]:
        """`function` as the processes call it: with their copy of the context first, if there is one."""
        return functools.partial(_call_with_context, function) if self.context is not None else function

    def _map_with_caller(self, function: Callable[..., Any], items: list[tuple]) -> Iterator[Any]:
        """`map` with this process as a worker: every item is sent to the processes, which take them from the
        front while this process takes them from the back, each item claimed once under a shared lock
        (`_claimed_call`), until the two meet; results in order, each as soon as it and those before are
        done. (Nothing is cancelled: a future cancelled in a pool that then breaks stops Python 3.11's
        clean-up of the pool.)"""
        remote, local, claims = self._in_processes(function), self._here(function), self._claims
        claims[0], claims[1] = 0, len(items)
        futures = [self._executor.submit(_claimed_call, remote, index, *args)
                   for index, args in enumerate(items)]
        local_results: dict[int, Any] = {}
        done = 0
        while True:
            while done < len(items) and done not in local_results and futures[done].done():
                yield futures[done].result()
                done += 1
            with claims.get_lock():
                if claims[1] - 1 < claims[0]:
                    break
                claims[1] -= 1
                index = claims[1]
            local_results[index] = _in_one_blas_thread(local, *items[index])
        for index in range(done, len(items)):
            yield local_results[index] if index in local_results else futures[index].result()

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exception: object) -> None:
        self.shutdown()

    def shutdown(self, wait: bool = True) -> None:
        """Ends the processes (queued calls cancelled); `wait`: until they have exited."""
        if self._executor is not None:
            self._executor.shutdown(wait=wait, cancel_futures=True)
