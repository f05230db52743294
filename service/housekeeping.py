"""Housekeeping of the data folder: finished jobs expire after a while unless pinned; free-space check.

`expire_finished_jobs` runs in every supervisor loop (local) or reaper loop (Celery), at most every
HOUSEKEEPING_SECONDS; deleting a job twice (several API processes) is harmless.
"""

from __future__ import annotations

import logging
import shutil
from datetime import timedelta

from service.layout import job_dir
from service.settings import ServiceSettings
from service.store.job_store import JobStore
from service.store.tables import utcnow

log = logging.getLogger(__name__)
HOUSEKEEPING_SECONDS = 60.0


def delete_job_and_files(store: JobStore, settings: ServiceSettings, job_id: str) -> None:
    """The job's row, its log and its folder (the job must not be running)."""
    store.delete(job_id)
    shutil.rmtree(job_dir(settings, job_id), ignore_errors=True)


def expire_finished_jobs(store: JobStore, settings: ServiceSettings) -> list[str]:
    """Deletes finished, unpinned jobs older than SFMNERF_JOB_RETENTION_MINUTES; returns their ids.

    A scene's child jobs expire only with their scene: a finished scene older than the retention whose
    jobs are all finished and unpinned is deleted whole (jobs, files and the scene)."""
    cutoff = utcnow() - timedelta(minutes=settings.job_retention_minutes)
    expired = []
    for scene in store.expired_scenes(cutoff):
        scene_jobs = store.scene_job_ids(scene)
        for job_id in scene_jobs:
            delete_job_and_files(store, settings, job_id)
        store.delete_scene(scene.id)
        expired += scene_jobs
    for job_id in store.expired(cutoff):
        delete_job_and_files(store, settings, job_id)
        expired.append(job_id)
    if expired:
        log.info(
            "expired %d finished job(s) older than %g minutes", len(expired), settings.job_retention_minutes
        )
    return expired


def disk_space_problem(settings: ServiceSettings) -> str | None:
    """Why new work would not fit on the data folder's disk, or None."""
    free = shutil.disk_usage(settings.data_dir).free
    if free < settings.min_free_disk_bytes:
        return (
            f"the server's disk has {free} bytes free, less than SFMNERF_MIN_FREE_DISK_BYTES="
            f"{settings.min_free_disk_bytes}; no new work is accepted until space is freed"
        )
    return None
