"""Where a job's files live: its folder under the data folder, its inputs and outputs, and the names of
the artefacts the service reads from the packages' outputs.

The artefact names are the packages' own (estimation.pipeline REPORT_NAME ..., neural.inference
RUN_CONFIG_FILE, neural.training METRICS_FILE); they are spelled here because those modules load OpenCV,
GTSAM or PyTorch, which the API process never imports. tests/service/test_layout.py holds them equal.
"""

from __future__ import annotations

from pathlib import Path

from service.settings import ServiceSettings

INPUT_DIR = "input"
OUTPUT_DIR = "output"
"""Reconstruction output folder, NeRF run folder, video or held-out renders of a job."""
WORKER_LOG_NAME = "worker.log"
"""stdout and stderr of a local job process, in its job folder."""
SPREAD_DIR = "spread"
"""A spread reconstruction's stage specifications, task claims and chunk results (one folder per attempt),
in its job folder: every Celery worker reads and writes them there (the data folder is shared)."""

RECONSTRUCTION_REPORT = "report.json"
"""estimation.pipeline.REPORT_NAME: what a reconstruction registered (in its output folder)."""
RECONSTRUCTION_EXPORTS = ("points.ply", "colmap.zip", "transforms.json")
"""The files a reconstruction's output serves (estimation.pipeline PLY_NAME and TRANSFORMS_NAME; colmap.zip is
the service's own archive of its sparse/ folder)."""
RUN_CONFIG = "config.json"
"""neural.inference.RUN_CONFIG_FILE: a NeRF run's configuration and camera."""
RUN_METRICS = "metrics.jsonl"
"""neural.training.METRICS_FILE: a NeRF run's metrics, one JSON object a line."""


def job_dir(settings: ServiceSettings, job_id: str) -> Path:
    return settings.jobs_dir / job_id


def input_dir(settings: ServiceSettings, job_id: str) -> Path:
    return job_dir(settings, job_id) / INPUT_DIR


def output_dir(settings: ServiceSettings, job_id: str) -> Path:
    """Reconstruction output folder, NeRF run folder, video or held-out renders of a job."""
    return job_dir(settings, job_id) / OUTPUT_DIR
