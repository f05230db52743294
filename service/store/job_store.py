"""The job store: jobs, their progress, results and log lines, the webhook outbox, supervisor leases and
scenes in one SQL database (SQLAlchemy 2), one table family per module of service.store.

SQLite (the default, a file in the data folder) and PostgreSQL both work. Several processes write to it:
the API, the local job processes and Celery workers.
"""

from __future__ import annotations

from service.store.jobs import JobRows
from service.store.leases import SupervisorLeases
from service.store.logs import JobLogs
from service.store.outbox import WebhookOutbox
from service.store.scenes import SceneRows


class JobStore(JobRows, JobLogs, WebhookOutbox, SupervisorLeases, SceneRows):
    """All reads and writes of the service's state; safe to use from several threads and processes.

    `migrate`: upgrade the schema first (the API and CLI do; job processes open an upgraded database).
    """
