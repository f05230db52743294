"""A local job process: `python -m service.worker JOB_ID ATTEMPT PARENT_PID`, started by the local executor.

It runs one job attempt and exits. It dies with the service (Linux: PR_SET_PDEATHSIG, elsewhere a watchdog
polling the parent), so a restarted service can re-queue the job without a stray process still writing.
"""

from __future__ import annotations

import os
import sys

from estimation.parallel import die_with_parent
from service.runner import execute
from service.settings import WORKER_SETTINGS_ENV, ServiceSettings
from service.store.job_store import JobStore


def main(argv: list[str] | None = None) -> int:
    job_id, attempt, parent_pid = (argv or sys.argv[1:])[:3]
    die_with_parent(int(parent_pid))
    settings = ServiceSettings.model_validate_json(os.environ[WORKER_SETTINGS_ENV])
    store = JobStore(settings.resolved_database_url, migrate=False)
    try:
        execute(store, job_id, int(attempt), settings)
    finally:
        store.dispose()
    return 0


if __name__ == "__main__":
    sys.exit(main())
