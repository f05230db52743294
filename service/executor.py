"""Executors: where jobs run. `local` (default): one supervised process per job; `celery`: Celery workers.

The local executor's supervisor thread starts queued jobs in fresh processes (`python -m service.worker`)
up to the configured concurrency, kills the process of a cancelled job or of one over its kind's maximum
runtime, and records how a job whose process ended without a result ended (cancelled or failed with the
reason) once that process has exited. A crash, an out-of-memory kill or a long NeRF run stays inside its
own process.

One owner per job: each supervisor holds a lease row (renewed several times per
SFMNERF_SUPERVISOR_LEASE_SECONDS) and claims jobs under it; several API processes on one database each
run their own jobs and never touch another's. A job whose supervisor's lease lapsed (or whose supervisor
process on this host is gone, e.g. after kill -9) is re-queued by any live supervisor, at start and
periodically (NeRF jobs resume from their checkpoint). On stop a supervisor kills its own job processes and
re-queues their jobs the same way, so a restart loses no job.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import IO, Protocol
from uuid import uuid4

from service.celery_config import RUN_JOB_TASK, make_celery
from service.housekeeping import HOUSEKEEPING_SECONDS, expire_finished_jobs
from service.job_end import complete_job, runtime_exceeded
from service.kinds import JobKind, JobState
from service.layout import WORKER_LOG_NAME, job_dir
from service.loop_thread import LoopThread
from service.settings import WORKER_SETTINGS_ENV, ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import Job

log = logging.getLogger(__name__)
SUPERVISOR_POLL_SECONDS = 0.25
HARD_LIMIT_MARGIN_SECONDS = 30.0
"""Celery's hard time limit lies this far beyond a job's soft limit (its maximum runtime)."""
WORKER_LOG_TAIL_BYTES = 600


class Executor(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...

    def submit(self, job_id: str) -> None:
        """A queued job is waiting in the store."""

    def cancel(self, job_id: str) -> None:
        """The store flagged the job cancelled (`JobStore.request_cancel`): stop it now."""

    def problem(self) -> str | None:
        """Why the queue is not usable right now, or None."""


def requeue_after_restart(store: JobStore, job: Job, why: str) -> None:
    """Puts a job that was running back in the queue; a NeRF job will resume from its last checkpoint."""
    resume = job.kind == JobKind.nerf
    if store.requeue(job.id, job.attempt, resume=resume):
        note = "; it resumes from its last checkpoint" if resume else "; it starts again"
        store.append_log(job.id, [f"{why}: attempt {job.attempt} was stopped and the job re-queued{note}"])


def describe_exit(returncode: int, worker_log: Path) -> str:
    """Why a job process ended without recording a result, from its exit status."""
    if returncode < 0:
        name = signal.Signals(-returncode).name if -returncode in signal.valid_signals() else str(-returncode)
        hint = " (killed: out of memory or kill -9)" if -returncode == signal.SIGKILL else ""
        return f"the job's worker process died: signal {name}{hint}"
    tail = _tail(worker_log)
    if returncode == 0:
        return "the job's worker process exited without recording a result"
    return f"the job's worker process exited with status {returncode}" + (f": {tail}" if tail else "")


def _tail(path: Path) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - WORKER_LOG_TAIL_BYTES))
            lines = f.read().decode(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return lines[-1] if lines else ""


@dataclass
class _JobProcess:
    process: subprocess.Popen
    attempt: int
    kind: str
    log_file: IO[bytes]
    started: float
    terminate_sent_at: float | None = None
    stop_reason: str | None = None
    """Why the supervisor stopped it (the maximum runtime); None: it ended by itself or was cancelled."""


class _Every:
    """True once per `seconds`, the first time `seconds` after it was made (a chore in a polling loop)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._last = time.monotonic()

    def due(self) -> bool:
        now = time.monotonic()
        if now - self._last < self.seconds:
            return False
        self._last = now
        return True


class LocalExecutor:
    """Runs each job in its own process, at most `settings.concurrency` at a time per API process."""

    def __init__(self, settings: ServiceSettings, store: JobStore) -> None:
        self.settings = settings
        self.store = store
        self.supervisor_id: str | None = None
        self._processes: dict[str, _JobProcess] = {}
        self._wake = threading.Event()
        self._supervision = LoopThread("sfmnerf-supervisor", self._loop)
        self._lease = _Every(settings.supervisor_lease_seconds / 3)
        self._housekeeping = _Every(HOUSEKEEPING_SECONDS)

    # ---- lifecycle -----------------------------------------------------------------------------------

    def start(self) -> None:
        self.supervisor_id = self.store.register_supervisor()
        self._take_over_orphans()
        self._supervision.start()

    def stop(self) -> None:
        self._supervision.stopping.set()
        self._wake.set()  # the loop may be waiting for work: it sees `stopping` at once
        self._supervision.stop()
        for job_id, running in list(self._processes.items()):
            running.process.kill()
            running.process.wait()
            running.log_file.close()
            job = self.store.get(job_id)
            if job is not None and job.attempt == running.attempt:
                requeue_after_restart(self.store, job, "the service stopped")
        self._processes.clear()
        if self.supervisor_id:
            self.store.release_lease(self.supervisor_id)

    def submit(self, job_id: str) -> None:
        self._wake.set()

    def cancel(self, job_id: str) -> None:
        self._wake.set()  # the owner (this or another API process) sees the job's cancel flag

    def problem(self) -> str | None:
        if not self._supervision.is_alive():
            return "the job supervisor is not running"
        return None

    # ---- the supervisor loop --------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._supervision.stopping.is_set():
            try:
                if self._lease.due():
                    self.store.renew_lease(self.supervisor_id)
                    self._take_over_orphans()
                self._reap()
                self._stop_cancelled_and_overdue()
                self._start_queued()
                if self._housekeeping.due():
                    expire_finished_jobs(self.store, self.settings)
            except Exception:  # a database hiccup must not end supervision
                log.exception("job supervisor iteration failed")
            self._wake.wait(SUPERVISOR_POLL_SECONDS)
            self._wake.clear()

    def _take_over_orphans(self) -> None:
        """Re-queues running jobs whose supervisor is gone (its lease lapsed or its process died)."""
        lease = timedelta(seconds=self.settings.supervisor_lease_seconds)
        for job in self.store.orphaned_running(lease):
            _kill_stray_worker(job)
            requeue_after_restart(self.store, job, "the service that ran it stopped")

    def _reap(self) -> None:
        for job_id, running in list(self._processes.items()):
            returncode = running.process.poll()
            if returncode is None:
                continue
            del self._processes[job_id]
            running.log_file.close()
            job = self.store.get(job_id)
            if job is None or job.attempt != running.attempt:
                continue
            if job.state != JobState.running:  # it recorded its own end (and marked its webhook due)
                continue
            if running.stop_reason:
                state, error = JobState.failed, running.stop_reason
            elif job.cancel_requested:
                state, error = JobState.cancelled, "cancelled"
            else:
                state = JobState.failed
                error = describe_exit(returncode, job_dir(self.settings, job_id) / WORKER_LOG_NAME)
            complete_job(self.store, self.settings, job_id, running.attempt, state, error=error)

    def _stop_cancelled_and_overdue(self) -> None:
        for job in self.store.cancel_requested_running(self.supervisor_id):
            running = self._processes.get(job.id)
            if running is None:  # claimed but its process never started: nothing to wait for
                complete_job(
                    self.store, self.settings, job.id, job.attempt, JobState.cancelled, error="cancelled"
                )
            else:
                self._terminate(running)
        now = time.monotonic()
        for running in self._processes.values():
            if running.stop_reason is None and now - running.started > self.settings.max_runtime_seconds(
                running.kind
            ):
                running.stop_reason = runtime_exceeded(
                    running.kind, self.settings.max_runtime_seconds(running.kind)
                )
            if running.stop_reason:
                self._terminate(running)

    def _terminate(self, running: _JobProcess) -> None:
        """SIGTERM, then SIGKILL after the grace period; its end is recorded when it has exited (_reap)."""
        now = time.monotonic()
        if running.terminate_sent_at is None:
            running.process.terminate()
            running.terminate_sent_at = now
        elif now - running.terminate_sent_at >= self.settings.cancel_grace_seconds:
            running.process.kill()

    def _start_queued(self) -> None:
        free = self.settings.concurrency - len(self._processes)
        if free <= 0:
            return
        for job_id, attempt in self.store.claim_next(free, worker="local", supervisor_id=self.supervisor_id):
            try:
                self._spawn(job_id, attempt)
            except OSError as error:
                complete_job(
                    self.store,
                    self.settings,
                    job_id,
                    attempt,
                    JobState.failed,
                    error=f"cannot start a job process: {error}",
                )

    def _spawn(self, job_id: str, attempt: int) -> None:
        job = self.store.get(job_id)
        folder = job_dir(self.settings, job_id)
        folder.mkdir(parents=True, exist_ok=True)
        log_file = open(folder / WORKER_LOG_NAME, "ab")  # noqa: SIM115 (closed when the process is reaped)
        env = {k: v for k, v in os.environ.items() if k != "SFMNERF_API_TOKEN"}  # jobs never need it
        env[WORKER_SETTINGS_ENV] = self.settings.to_worker_json()
        threads = str(self.settings.threads_per_job())
        env.update(OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads)
        process = subprocess.Popen(
            [sys.executable, "-m", "service.worker", job_id, str(attempt), str(os.getpid())],
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=str(Path(__file__).resolve().parents[1]),
        )
        self._processes[job_id] = _JobProcess(
            process=process, attempt=attempt, kind=job.kind, log_file=log_file, started=time.monotonic()
        )
        self.store.set_process(job_id, attempt, process.pid, worker="local")


def _kill_stray_worker(job: Job) -> None:
    """Kills a job process a crashed service left behind (only if it is really our worker for this job)."""
    if not job.pid:
        return
    try:
        with open(f"/proc/{job.pid}/cmdline", "rb") as f:
            cmdline = f.read().split(b"\0")
    except OSError:
        return
    if b"service.worker" in cmdline and job.id.encode() in cmdline:
        with contextlib.suppress(OSError):
            os.kill(job.pid, signal.SIGKILL)


class CeleryExecutor:
    """Sends jobs to Celery workers; a reaper marks jobs whose worker stopped heartbeating as failed."""

    def __init__(self, settings: ServiceSettings, store: JobStore) -> None:
        self.settings = settings
        self.store = store
        self.celery = make_celery(settings)
        self._housekeeping = _Every(HOUSEKEEPING_SECONDS)
        self._reaper = LoopThread("sfmnerf-reaper", self._reap_loop)

    def start(self) -> None:
        self._reaper.start()

    def stop(self) -> None:
        self._reaper.stop()

    def submit(self, job_id: str) -> None:
        job = self.store.get(job_id)
        task_id = f"{job_id}-{uuid4().hex[:8]}"
        self.store.set_task_id(job_id, task_id)
        limit = self.settings.max_runtime_seconds(job.kind)
        # The soft limit interrupts the job (it fails with the reason); the hard one kills a job that
        # does not stop, and the task_failure handler records the same reason.
        self.celery.send_task(
            RUN_JOB_TASK,
            args=[job_id],
            task_id=task_id,
            soft_time_limit=limit,
            time_limit=limit + self.settings.cancel_grace_seconds + HARD_LIMIT_MARGIN_SECONDS,
        )

    def cancel(self, job_id: str) -> None:
        job = self.store.get(job_id)
        if job is None or not job.task_id:
            return
        if job.state == JobState.running:
            self.celery.control.revoke(job.task_id, terminate=True, signal="SIGKILL")
            complete_job(
                self.store, self.settings, job.id, job.attempt, JobState.cancelled, error="cancelled"
            )
        else:
            self.celery.control.revoke(job.task_id)

    def problem(self) -> str | None:
        try:
            with self.celery.connection_for_write() as connection:
                connection.ensure_connection(max_retries=1, timeout=2)
        except Exception as error:  # kombu raises many kinds
            return f"the broker is unreachable ({type(error).__name__})"
        return None

    def _reap_loop(self) -> None:
        timeout = timedelta(seconds=self.settings.heartbeat_timeout_seconds)
        while not self._reaper.stopping.wait(self.settings.heartbeat_seconds):
            try:
                for job in self.store.stale_running(timeout):
                    error = (
                        f"the worker ({job.worker}) stopped sending heartbeats for "
                        f"{self.settings.heartbeat_timeout_seconds:g} s: it died or lost the database"
                    )
                    complete_job(self.store, self.settings, job.id, job.attempt, JobState.failed, error=error)
                if self._housekeeping.due():
                    expire_finished_jobs(self.store, self.settings)
            except Exception:
                log.exception("heartbeat reaper iteration failed")


def make_executor(settings: ServiceSettings, store: JobStore) -> Executor:
    if settings.executor == "celery":
        return CeleryExecutor(settings, store)
    return LocalExecutor(settings, store)
