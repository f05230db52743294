"""The job store (service.store.job_store.JobStore) and its tables, one module per table family: jobs and
their state transitions, log lines, the webhook outbox, supervisor leases, scenes."""

from service.store.job_store import JobStore
from service.store.leases import process_exists
from service.store.tables import Base, Job, LogLine, Scene, Supervisor, UTCDateTime, new_job_id, utcnow

__all__ = [
    "Base",
    "Job",
    "JobStore",
    "LogLine",
    "Scene",
    "Supervisor",
    "UTCDateTime",
    "new_job_id",
    "process_exists",
    "utcnow",
]
