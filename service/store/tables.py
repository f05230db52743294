"""The job store's tables (SQLAlchemy 2 declarative models): jobs, their log lines, supervisor leases and
scenes. The schema is created and upgraded by the Alembic migrations in `service/migrations`."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, NamedTuple
from uuid import uuid4

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, TypeDecorator
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from service.kinds import JobState


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_job_id() -> str:
    return uuid4().hex


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Any) -> datetime | None:
        return None if value is None else value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Any) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    pass


class Job(Base):
    """One unit of work: a reconstruction, a NeRF training run or an orbit video."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    kind: Mapped[str] = mapped_column(String(32), index=True)
    state: Mapped[str] = mapped_column(String(16), index=True, default=JobState.queued)
    stage: Mapped[str | None] = mapped_column(String(200), default=None)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, index=True)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=None)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=None)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    params: Mapped[dict] = mapped_column(JSON, default=dict)
    result: Mapped[dict | None] = mapped_column(JSON, default=None)
    source_job_id: Mapped[str | None] = mapped_column(String(32), index=True, default=None)
    retry_of: Mapped[str | None] = mapped_column(String(32), default=None)
    webhook_url: Mapped[str | None] = mapped_column(Text, default=None)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    resume: Mapped[bool] = mapped_column(Boolean, default=False)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    worker: Mapped[str | None] = mapped_column(String(200), default=None)
    pid: Mapped[int | None] = mapped_column(Integer, default=None)
    task_id: Mapped[str | None] = mapped_column(String(100), default=None)
    supervisor_id: Mapped[str | None] = mapped_column(String(64), index=True, default=None)
    pinned: Mapped[bool] = mapped_column(Boolean, default=False)
    owner: Mapped[str | None] = mapped_column(String(64), index=True, default=None)
    # The webhook outbox (service/webhooks.py): pending -> sending (claimed at) -> delivered | failed.
    webhook_state: Mapped[str | None] = mapped_column(String(16), index=True, default=None)
    webhook_claimed_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=None)


class Supervisor(Base):
    """A local executor's lease: it owns the jobs it claimed while its heartbeat is fresh."""

    __tablename__ = "supervisors"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    host: Mapped[str] = mapped_column(String(255))
    pid: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    heartbeat_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class LogLine(Base):
    """One line of a job's log; a job's lines are ordered by id, and `offset` counts lines."""

    __tablename__ = "job_logs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    line: Mapped[str] = mapped_column(Text)


class Scene(Base):
    """Photos to novel views: a reconstruction, a NeRF on its poses, then an orbit video and held-out
    renders, each a child job; `stage` names the step the scene is at, `log` its own events."""

    __tablename__ = "scenes"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    state: Mapped[str] = mapped_column(String(16), index=True, default=JobState.running)
    stage: Mapped[str] = mapped_column(String(32), default="reconstruction")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, index=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, default=None)
    error: Mapped[str | None] = mapped_column(Text, default=None)
    params: Mapped[dict] = mapped_column(JSON, default=dict)
    reconstruction_job_id: Mapped[str | None] = mapped_column(String(32), default=None)
    nerf_job_id: Mapped[str | None] = mapped_column(String(32), default=None)
    video_job_id: Mapped[str | None] = mapped_column(String(32), default=None)
    evaluation_job_id: Mapped[str | None] = mapped_column(String(32), default=None)
    log: Mapped[list] = mapped_column(JSON, default=list)


SCENE_CHILD_COLUMNS = (
    Scene.reconstruction_job_id,
    Scene.nerf_job_id,
    Scene.video_job_id,
    Scene.evaluation_job_id,
)
"""A scene's child jobs, one column per job, in the order of its stages."""


class SceneChild(NamedTuple):
    """Where a scene records a child job: the scene's id and the column's name (one of SCENE_CHILD_COLUMNS).
    The job and this record are written in one transaction, so a crash cannot leave a child job that its
    scene does not know of (and would start again)."""

    scene_id: str
    column: str
