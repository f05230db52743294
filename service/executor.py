"""Executors: where jobs run. `local` (default): one supervised process per job; `celery`: Celery workers.

The local executor's supervisor thread starts queued jobs in fresh processes (`python -m service.worker`)
up to the configured concurrency, kills the process of a cancelled job, and marks a job whose process died
failed with the reason. A crash, an out-of-memory kill or a long NeRF run stays inside its own process.
On start it re-queues the jobs a previous service left running (NeRF jobs resume from their checkpoint);
on stop it kills its job processes and re-queues their jobs the same way, so a restart loses no job.
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

from service import webhooks
from service.db import TERMINAL_STATES, Job, JobKind, JobState, JobStore
from service.jobs import job_dir
from service.settings import WORKER_SETTINGS_ENV, ServiceSettings

log = logging.getLogger(__name__)
SUPERVISOR_POLL_SECONDS = 0.25
WORKER_LOG_NAME = "worker.log"
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
    log_file: IO[bytes]
    terminate_sent_at: float | None = None


class LocalExecutor:
    """Runs each job in its own process, at most `settings.concurrency` at a time."""

    def __init__(self, settings: ServiceSettings, store: JobStore) -> None:
        self.settings = settings
        self.store = store
        self._processes: dict[str, _JobProcess] = {}
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    # ---- lifecycle -----------------------------------------------------------------------------------

    def start(self) -> None:
        for job in self.store.running():
            _kill_stray_worker(job)
            requeue_after_restart(self.store, job, "the service restarted")
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="sfmnerf-supervisor", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        self._wake.set()
        if self._thread:
            self._thread.join(timeout=10)
        for job_id, running in list(self._processes.items()):
            running.process.kill()
            running.process.wait()
            running.log_file.close()
            job = self.store.get(job_id)
            if job is not None and job.attempt == running.attempt:
                requeue_after_restart(self.store, job, "the service stopped")
        self._processes.clear()

    def submit(self, job_id: str) -> None:
        self._wake.set()

    def cancel(self, job_id: str) -> None:
        self._wake.set()

    def problem(self) -> str | None:
        if self._thread is None or not self._thread.is_alive():
            return "the job supervisor is not running"
        return None

    def pid_of(self, job_id: str) -> int | None:
        running = self._processes.get(job_id)
        return running.process.pid if running else None

    # ---- the supervisor loop --------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                self._reap()
                self._kill_cancelled()
                self._start_queued()
            except Exception:  # a database hiccup must not end supervision
                log.exception("job supervisor iteration failed")
            self._wake.wait(SUPERVISOR_POLL_SECONDS)
            self._wake.clear()

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
            if job.state in TERMINAL_STATES:  # it recorded its own end; its webhook is sent from here
                webhooks.enqueue_delivery(self.store, job_id, self.settings)
                continue
            if job.state != JobState.running:
                continue
            if job.cancel_requested:
                state, error = JobState.cancelled, "cancelled"
            else:
                state = JobState.failed
                error = describe_exit(returncode, job_dir(self.settings, job_id) / WORKER_LOG_NAME)
            if self.store.finish(job_id, running.attempt, state, error=error):
                self.store.append_log(job_id, [f"finished: {state} ({error})"])
                webhooks.enqueue_delivery(self.store, job_id, self.settings)

    def _kill_cancelled(self) -> None:
        for job in self.store.cancel_requested_running():
            running = self._processes.get(job.id)
            if running is None:  # claimed but never started, or not ours: nothing to kill
                if self.store.finish(job.id, job.attempt, JobState.cancelled, error="cancelled"):
                    webhooks.enqueue_delivery(self.store, job.id, self.settings)
                continue
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
        for job_id in self.store.queued_ids(free):
            attempt = self.store.claim(job_id, worker="local")
            if attempt is None:
                continue
            try:
                self._spawn(job_id, attempt)
            except OSError as error:
                self.store.finish(
                    job_id, attempt, JobState.failed, error=f"cannot start a job process: {error}"
                )

    def _spawn(self, job_id: str, attempt: int) -> None:
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
        self._processes[job_id] = _JobProcess(process=process, attempt=attempt, log_file=log_file)
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
        from service.celery_app import make_celery

        self.settings = settings
        self.store = store
        self.celery = make_celery(settings)
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._stopping.clear()
        self._thread = threading.Thread(target=self._reap_loop, name="sfmnerf-reaper", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread:
            self._thread.join(timeout=10)

    def submit(self, job_id: str) -> None:
        from service.celery_app import RUN_JOB_TASK

        task_id = f"{job_id}-{uuid4().hex[:8]}"
        self.store.set_task_id(job_id, task_id)
        self.celery.send_task(RUN_JOB_TASK, args=[job_id], task_id=task_id)

    def cancel(self, job_id: str) -> None:
        job = self.store.get(job_id)
        if job is None or not job.task_id:
            return
        if job.state == JobState.running:
            self.celery.control.revoke(job.task_id, terminate=True, signal="SIGKILL")
            if self.store.finish(job.id, job.attempt, JobState.cancelled, error="cancelled"):
                self.store.append_log(job.id, ["finished: cancelled (its worker process was killed)"])
                webhooks.enqueue_delivery(self.store, job.id, self.settings)
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
        while not self._stopping.wait(self.settings.heartbeat_seconds):
            try:
                for job in self.store.stale_running(timeout):
                    error = (
                        f"the worker ({job.worker}) stopped sending heartbeats for "
                        f"{self.settings.heartbeat_timeout_seconds:g} s: it died or lost the database"
                    )
                    if self.store.finish(job.id, job.attempt, JobState.failed, error=error):
                        webhooks.enqueue_delivery(self.store, job.id, self.settings)
            except Exception:
                log.exception("heartbeat reaper iteration failed")


def make_executor(settings: ServiceSettings, store: JobStore) -> Executor:
    if settings.executor == "celery":
        return CeleryExecutor(settings, store)
    return LocalExecutor(settings, store)
