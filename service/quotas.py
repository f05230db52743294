"""Per-client limits and fair turns: one client's backlog never holds another's work.

Named clients (SFMNERF_CLIENTS_FILE) may have at most SFMNERF_MAX_QUEUED_JOBS_PER_CLIENT jobs waiting
(more: 429 with Retry-After) and at most SFMNERF_MAX_DISK_BYTES_PER_CLIENT in their jobs' folders (more:
507); the admin token and an open service (no tokens) have no quota. The queue hands out its slots in
turns: it puts each client's oldest waiting job in line behind the oldest waiting job of every
client with fewer jobs running (service.fair_queue), so 200 jobs of one client wait behind one job of
another.
"""

from __future__ import annotations

import os
from pathlib import Path

from service.auth import Client
from service.errors import busy, no_space
from service.kinds import JobState
from service.layout import job_dir
from service.settings import ServiceSettings
from service.store.job_store import JobStore

QUEUE_RETRY_AFTER_SECONDS = 30
MAX_JOBS_COUNTED = 10_000


def folder_bytes(folder: Path) -> int:
    """Bytes of the files under folder (links not followed); 0 when it does not exist."""
    total, pending = 0, [folder]
    while pending:
        try:
            entries = list(os.scandir(pending.pop()))
        except OSError:
            continue
        for entry in entries:
            if entry.is_dir(follow_symlinks=False):
                pending.append(Path(entry.path))
            elif entry.is_file(follow_symlinks=False):
                total += entry.stat(follow_symlinks=False).st_size
    return total


def check_client_quota(store: JobStore, client: Client, settings: ServiceSettings) -> None:
    """429 when the client has its most jobs waiting, 507 when its jobs' files reach its disk quota."""
    if client.admin or client.name is None:
        return
    _, queued = store.list(state=JobState.queued, owner=client.name, limit=1)
    if queued >= settings.max_queued_jobs_per_client:
        raise busy(
            f"client {client.name} has {queued} jobs waiting, the limit "
            f"SFMNERF_MAX_QUEUED_JOBS_PER_CLIENT={settings.max_queued_jobs_per_client}; "
            f"retry after {QUEUE_RETRY_AFTER_SECONDS} s",
            QUEUE_RETRY_AFTER_SECONDS,
        )
    jobs, _ = store.list(owner=client.name, limit=MAX_JOBS_COUNTED)
    used = sum(folder_bytes(job_dir(settings, job.id)) for job in jobs)
    if used >= settings.max_disk_bytes_per_client:
        raise no_space(
            f"client {client.name}'s jobs take {used} bytes, the limit SFMNERF_MAX_DISK_BYTES_PER_CLIENT="
            f"{settings.max_disk_bytes_per_client}; delete finished jobs to free space"
        )
