"""A local job process: `python -m service.worker JOB_ID ATTEMPT PARENT_PID`, started by the local executor.

It runs one job attempt and exits. It dies with the service (Linux: PR_SET_PDEATHSIG, elsewhere a watchdog
polling the parent), so a restarted service can re-queue the job without a stray process still writing.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

from service.settings import WORKER_SETTINGS_ENV, ServiceSettings

PR_SET_PDEATHSIG = 1
PARENT_POLL_SECONDS = 1.0


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


def main(argv: list[str] | None = None) -> int:
    job_id, attempt, parent_pid = (argv or sys.argv[1:])[:3]
    die_with_parent(int(parent_pid))
    from service.db import JobStore
    from service.runner import execute

    settings = ServiceSettings.model_validate_json(os.environ[WORKER_SETTINGS_ENV])
    store = JobStore(settings.resolved_database_url, migrate=False)
    try:
        execute(store, job_id, int(attempt), settings)
    finally:
        store.dispose()
    return 0


if __name__ == "__main__":
    sys.exit(main())
