"""Worker processes: the worker count, results in order and equal to the calling process's, the pool's
context in every call (received once by each process, also when shared after the start), one BLAS thread
per process, an error (not a hang) when a process dies, and no process outliving the one that started it;
with the calling process as one of the workers, the same."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

from estimation.parallel import (
    WorkerPool,
    _openblas_thread_functions,
    available_cores,
    blas_threads,
    resolve_workers,
)

ROOT = Path(__file__).resolve().parents[2]


def test_zero_workers_means_one_per_available_core():
    assert resolve_workers(0) == available_cores() >= 1
    assert resolve_workers(3) == 3


def test_processes_return_what_the_calling_process_computes_in_order():
    with WorkerPool(2, modules=("estimation.two_view.geometry",)) as pool:
        assert pool.workers == 2
        assert list(pool.map(divmod, range(40), [7] * 40)) == [divmod(n, 7) for n in range(40)]
        assert len({os.getpid(), *pool.map(_pid, range(40))}) >= 2     # the work ran elsewhere
    assert list(WorkerPool(1).map(divmod, range(5), [2] * 5)) == [divmod(n, 2) for n in range(5)]


def _pid_after(caller: int, markers: str, seconds: float) -> int:
    """This process's id after `seconds`; a process leaves a marker named by its id in `markers` first, and
    the caller waits (at most 20 s) for two, so that each process takes items however slowly it started."""
    if os.getpid() != caller:
        (Path(markers) / str(os.getpid())).touch()
    deadline = time.monotonic() + 20
    while os.getpid() == caller and len(os.listdir(markers)) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(seconds)
    return os.getpid()


def test_with_the_caller_working_one_process_fewer_starts_and_the_caller_takes_items_from_the_back(tmp_path):
    with WorkerPool(3, caller_works=True) as pool:
        assert (pool.workers, pool.processes) == (3, 2)
        assert list(pool.map(divmod, range(40), [7] * 40)) == [divmod(n, 7) for n in range(40)]
        pids = list(pool.map(_pid_after, [os.getpid()] * 40, [str(tmp_path)] * 40, [0.02] * 40))
    mine = [k for k, pid in enumerate(pids) if pid == os.getpid()]
    assert mine and mine == list(range(mine[0], 40))      # a run at the back, no item twice or left out
    assert len(set(pids)) == 3


def test_with_the_caller_working_the_context_and_one_blas_thread_hold_in_the_caller_too():
    environment, threads = _blas_threads(0)
    with WorkerPool(2, context=100, caller_works=True) as pool:
        assert list(pool.map(divmod, range(1, 30))) == [divmod(100, n) for n in range(1, 30)]
    with WorkerPool(2, caller_works=True) as pool:
        outcomes = list(pool.map(_blas_threads, range(8)))
    assert all(set(child_threads) == {1} for _, child_threads in outcomes)
    assert _blas_threads(0) == (environment, threads)


def _exit_unless_in(caller: int, marker: str) -> int:
    """Ends this process, leaving `marker`, unless it is `caller`; the caller waits for the marker (at most
    20 s), so that it cannot take every item before a slow-starting process takes one."""
    if os.getpid() != caller:
        Path(marker).touch()
        os._exit(3)
    deadline = time.monotonic() + 20
    while not os.path.exists(marker) and time.monotonic() < deadline:
        time.sleep(0.01)
    return caller


def test_with_the_caller_working_a_process_that_dies_still_breaks_the_pool(tmp_path):
    started = time.monotonic()
    with pytest.raises(BrokenProcessPool), WorkerPool(2, caller_works=True) as pool:
        list(pool.map(_exit_unless_in, [os.getpid()] * 8, [str(tmp_path / "died")] * 8))
    assert time.monotonic() - started < 30


def test_every_call_gets_the_pool_context_first_in_the_processes_and_in_the_calling_process():
    for workers in (2, 1):
        with WorkerPool(workers, context=100) as pool:
            assert list(pool.map(divmod, range(1, 30))) == [divmod(100, n) for n in range(1, 30)]


_received: list[int] = []
"""Values of the `Received` objects unpickled in this process."""


class Received:
    """A context that counts its arrivals in each process (unpickled there: `__setstate__`)."""

    def __init__(self, value: int) -> None:
        self.value = value

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        _received.append(self.value)


def _receipts(context: Received, _: int) -> tuple[int, int, list[int]]:
    time.sleep(0.01)
    return os.getpid(), context.value, list(_received)


def test_a_context_shared_after_the_start_reaches_each_process_exactly_once():
    with WorkerPool(2) as pool:
        for value in (7, 8):
            pool.share(Received(value))
            outcomes = list(pool.map(_receipts, range(40)))
            assert {context for _, context, _ in outcomes} == {value}
            assert len({pid for pid, _, _ in outcomes}) == 2
            assert all(received == list(range(7, value + 1)) for _, _, received in outcomes)
    pool = WorkerPool(1)
    pool.share(Received(9))                                       # kept as it is, in this process
    assert [context for _, context, _ in pool.map(_receipts, range(3))] == [9] * 3


class Fatal:
    """A context whose arrival kills the process it reaches."""

    def __init__(self) -> None:
        self.state = "pickled"                          # an empty state would not be set on arrival

    def __setstate__(self, state: dict) -> None:
        os._exit(3)


def _exit(_: int) -> None:
    os._exit(3)


@pytest.mark.parametrize("crash", ["while receiving the context", "in an item"])
def test_a_process_that_dies_breaks_the_pool_with_an_error_not_a_hang(crash):
    started = time.monotonic()
    with pytest.raises(BrokenProcessPool), WorkerPool(2) as pool:
        if crash == "in an item":
            list(pool.map(_exit, range(4)))
        else:
            pool.share(Fatal())
    assert time.monotonic() - started < 30             # not the 120 s a process waits for the others


def _blas_threads(_: int) -> tuple[str | None, list[int]]:
    """OPENBLAS_NUM_THREADS and the thread count of each OpenBLAS loaded here."""
    return os.environ.get("OPENBLAS_NUM_THREADS"), [get() for get, _ in _openblas_thread_functions()]


def test_items_run_on_one_blas_thread_and_the_calling_process_keeps_its_own():
    environment, threads = _blas_threads(0)
    assert threads, "numpy's OpenBLAS is found"
    with WorkerPool(2) as pool:
        for child_environment, child_threads in pool.map(_blas_threads, range(4)):
            assert child_environment == "1" and child_threads and set(child_threads) == {1}
    assert list(WorkerPool(1).map(_blas_threads, range(2))) == [(environment, [1] * len(threads))] * 2
    assert _blas_threads(0) == (environment, threads)                    # restored after
    with blas_threads(1):
        assert _blas_threads(0)[1] == [1] * len(threads)
    assert _blas_threads(0)[1] == threads


def _slow_blas_environment(_: int) -> str | None:
    time.sleep(0.05)
    return os.environ.get("OPENBLAS_NUM_THREADS")


def test_every_process_is_spawned_before_any_takes_an_item(monkeypatch):
    """ProcessPoolExecutor spawns a process at a submit only while none is idle: had the first process
    finished its start-up item before the second submit (as under load, with a large context), the second
    would be spawned at the first map, outside the one-BLAS-thread environment (and the hidden __main__)."""
    submit, calls = ProcessPoolExecutor.submit, []

    def slow_start(self, *args, **kwargs):
        future = submit(self, *args, **kwargs)
        calls.append(None)
        if len(calls) == 1:
            time.sleep(2.0)        # time enough for the first process to start and finish its item
        return future

    monkeypatch.setattr(ProcessPoolExecutor, "submit", slow_start)
    with WorkerPool(2) as pool:
        assert set(pool.map(_slow_blas_environment, range(40))) == {"1"}


def _pid(_: int) -> int:
    time.sleep(0.01)
    return os.getpid()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"      # a zombie has exited
    except FileNotFoundError:
        return False


def test_worker_processes_die_with_the_process_that_started_them(tmp_path):
    # A script without the __main__ guard: the processes must not run it again.
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent("""
        import multiprocessing, time
        from estimation.parallel import WorkerPool
        pool = WorkerPool(2)
        print(*(child.pid for child in multiprocessing.active_children()), flush=True)
        time.sleep(60)
    """))
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, "PYTHONPATH": str(ROOT)})
    children = [int(pid) for pid in parent.stdout.readline().split()]
    assert len(children) == 2
    assert all(_alive(pid) for pid in children)
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in children)
