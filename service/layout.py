"""Where a job's files live: its folder under the data folder, its inputs and outputs, and the names of
the artefacts the service reads from the packages' outputs (the packages' own, from their import-free
`artefacts` modules: the API process never loads OpenCV, GTSAM or PyTorch)."""

from __future__ import annotations

from pathlib import Path

from estimation.artefacts import PLY_NAME, REPORT_NAME, TRANSFORMS_NAME
from neural.artefacts import METRICS_FILE, RUN_CONFIG_FILE
from service.settings import ServiceSettings

INPUT_DIR = "input"
OUTPUT_DIR = "output"
"""Reconstruction output folder, NeRF run folder, video or held-out renders of a job."""
WORKER_LOG_NAME = "worker.log"
"""stdout and stderr of a local job process, in its job folder."""
SPREAD_DIR = "spread"
"""A spread reconstruction's stage specifications, task claims and chunk results (one folder per attempt),
in its job folder: every Celery worker reads and writes them there (the data folder is shared)."""

RECONSTRUCTION_REPORT = REPORT_NAME
"""What a reconstruction registered (in its output folder)."""
COLMAP_ARCHIVE = "colmap.zip"
"""The service's own archive of a reconstruction's sparse/ folder."""
RECONSTRUCTION_EXPORTS = (PLY_NAME, COLMAP_ARCHIVE, TRANSFORMS_NAME)
"""The files a reconstruction's output serves."""
RUN_CONFIG = RUN_CONFIG_FILE
"""A NeRF run's configuration and camera."""
RUN_METRICS = METRICS_FILE
"""A NeRF run's metrics, one JSON object a line."""


def job_dir(settings: ServiceSettings, job_id: str) -> Path:
    return settings.jobs_dir / job_id


def input_dir(settings: ServiceSettings, job_id: str) -> Path:
    return job_dir(settings, job_id) / INPUT_DIR


def output_dir(settings: ServiceSettings, job_id: str) -> Path:
    """Reconstruction output folder, NeRF run folder, video or held-out renders of a job."""
    return job_dir(settings, job_id) / OUTPUT_DIR
