"""The job store: jobs, their progress, results and log lines in a SQL database (SQLAlchemy 2).

SQLite (the default, a file in the data folder) and PostgreSQL both work. Several processes write to it:
the API, the local job processes and Celery workers. Every write a job process makes is fenced by the
job's `attempt` number, so a worker that lost its job (cancelled, re-queued after a restart) cannot
overwrite the state its successor writes.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any
from uuid import uuid4

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    TypeDecorator,
    create_engine,
    delete,
    event,
    func,
    select,
    text,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker


class JobState(enum.StrEnum):
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"
    cancelled = "cancelled"


TERMINAL_STATES = frozenset({JobState.succeeded, JobState.failed, JobState.cancelled})


class JobKind(enum.StrEnum):
    reconstruction = "reconstruction"
    nerf = "nerf"
    video = "video"


def utcnow() -> datetime:
    return datetime.now(UTC)


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
    owner: Mapped[str | None] = mapped_column(String(64), index=True, default=None)


class LogLine(Base):
    """One line of a job's log; a job's lines are ordered by id, and `offset` counts lines."""

    __tablename__ = "job_logs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    line: Mapped[str] = mapped_column(Text)


def _make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 60})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
            # WAL lets the API read while job processes write; the busy timeout serialises writers.
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA busy_timeout=60000")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


class JobStore:
    """All reads and writes of jobs and their logs; safe to use from several threads and processes."""

    def __init__(self, url: str) -> None:
        if url.startswith("sqlite:///"):
            from pathlib import Path

            Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
        self.engine = _make_engine(url)
        Base.metadata.create_all(self.engine)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def dispose(self) -> None:
        self.engine.dispose()

    def ping(self) -> None:
        """Raises when the database is unreachable."""
        with self.engine.connect() as connection:
            connection.execute(text("SELECT 1"))

    # ---- creation and queries -------------------------------------------------------------------------

    def create(
        self,
        kind: JobKind,
        params: dict,
        *,
        job_id: str | None = None,
        source_job_id: str | None = None,
        retry_of: str | None = None,
        webhook_url: str | None = None,
        owner: str | None = None,
    ) -> Job:
        job = Job(
            id=job_id or new_job_id(),
            kind=str(kind),
            state=JobState.queued,
            params=params,
            source_job_id=source_job_id,
            retry_of=retry_of,
            webhook_url=webhook_url,
            owner=owner,
            created_at=utcnow(),
        )
        with self._sessions.begin() as session:
            session.add(job)
        return job

    def get(self, job_id: str) -> Job | None:
        with self._sessions() as session:
            return session.get(Job, job_id)

    def list(
        self,
        *,
        kind: str | None = None,
        state: str | None = None,
        owner: str | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> tuple[list[Job], int]:
        """Jobs newest first; only `owner`'s when given."""
        query = select(Job)
        if owner is not None:
            query = query.where(Job.owner == owner)
        if kind:
            query = query.where(Job.kind == kind)
        if state:
            query = query.where(Job.state == state)
        with self._sessions() as session:
            total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
            rows = session.scalars(
                query.order_by(Job.created_at.desc(), Job.id).limit(limit).offset(offset)
            ).all()
        return list(rows), int(total)

    def count(self, state: JobState) -> int:
        with self._sessions() as session:
            return int(session.scalar(select(func.count()).where(Job.state == state)) or 0)

    def queued_ids(self, limit: int) -> list[str]:
        with self._sessions() as session:
            query = select(Job.id).where(Job.state == JobState.queued).order_by(Job.created_at).limit(limit)
            return list(session.scalars(query).all())

    def running(self) -> list[Job]:
        with self._sessions() as session:
            return list(session.scalars(select(Job).where(Job.state == JobState.running)).all())

    def jobs_with_source(self, source_job_id: str, kind: JobKind | None = None) -> list[Job]:
        query = select(Job).where(Job.source_job_id == source_job_id)
        if kind:
            query = query.where(Job.kind == kind)
        with self._sessions() as session:
            return list(session.scalars(query.order_by(Job.created_at.desc())).all())

    # ---- state transitions ----------------------------------------------------------------------------

    def claim(self, job_id: str, worker: str, pid: int | None = None) -> int | None:
        """queued -> running for one worker; returns the new attempt number, None if not claimable."""
        with self._sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None or job.state != JobState.queued or job.cancel_requested:
                return None
            now = utcnow()
            attempt = job.attempt + 1
            result = session.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == JobState.queued, Job.attempt == job.attempt)
                .values(
                    state=JobState.running,
                    attempt=attempt,
                    started_at=now,
                    heartbeat_at=now,
                    finished_at=None,
                    error=None,
                    worker=worker,
                    pid=pid,
                    stage="starting",
                )
            )
            return attempt if result.rowcount == 1 else None

    def set_process(self, job_id: str, attempt: int, pid: int | None, worker: str) -> None:
        self._update_running(job_id, attempt, pid=pid, worker=worker)

    def set_task_id(self, job_id: str, task_id: str) -> None:
        with self._sessions.begin() as session:
            session.execute(update(Job).where(Job.id == job_id).values(task_id=task_id))

    def report_progress(self, job_id: str, attempt: int, stage: str, progress: float) -> bool:
        """Writes stage and progress; False when this attempt no longer owns the job."""
        return self._update_running(
            job_id, attempt, stage=stage[:200], progress=min(max(progress, 0.0), 1.0), heartbeat_at=utcnow()
        )

    def heartbeat(self, job_id: str, attempt: int) -> tuple[bool, bool]:
        """Refreshes the heartbeat; returns (still owned by this attempt, cancel requested)."""
        owned = self._update_running(job_id, attempt, heartbeat_at=utcnow())
        job = self.get(job_id)
        return owned, bool(job and job.cancel_requested)

    def finish(
        self,
        job_id: str,
        attempt: int,
        state: JobState,
        *,
        error: str | None = None,
        result: dict | None = None,
    ) -> bool:
        """running -> a terminal state, only for the attempt that runs it."""
        values: dict[str, Any] = {"state": state, "finished_at": utcnow(), "error": error, "pid": None}
        if state == JobState.succeeded:
            values.update(progress=1.0, stage="done")
        if result is not None:
            values["result"] = result
        return self._update_running(job_id, attempt, **values)

    def requeue(self, job_id: str, attempt: int, *, resume: bool) -> bool:
        """running -> queued (the service restarted under it); a NeRF job resumes from its checkpoint."""
        return self._update_running(
            job_id, attempt, state=JobState.queued, resume=resume, pid=None, stage="re-queued", worker=None
        )

    def request_cancel(self, job_id: str) -> Job | None:
        """A queued job is cancelled at once; a running one is flagged for its executor to kill."""
        with self._sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None:
                return None
            if job.state == JobState.queued:
                job.state = JobState.cancelled
                job.finished_at = utcnow()
                job.cancel_requested = True
                job.stage = "cancelled"
            elif job.state == JobState.running:
                job.cancel_requested = True
            return job

    def cancel_requested_running(self) -> list[Job]:
        with self._sessions() as session:
            query = select(Job).where(Job.state == JobState.running, Job.cancel_requested.is_(True))
            return list(session.scalars(query).all())

    def stale_running(self, older_than: timedelta) -> list[Job]:
        cutoff = utcnow() - older_than
        with self._sessions() as session:
            query = select(Job).where(Job.state == JobState.running, Job.heartbeat_at < cutoff)
            return list(session.scalars(query).all())

    def delete(self, job_id: str) -> bool:
        with self._sessions.begin() as session:
            session.execute(delete(LogLine).where(LogLine.job_id == job_id))
            return session.execute(delete(Job).where(Job.id == job_id)).rowcount == 1

    def _update_running(self, job_id: str, attempt: int, **values: Any) -> bool:
        with self._sessions.begin() as session:
            result = session.execute(
                update(Job)
                .where(Job.id == job_id, Job.attempt == attempt, Job.state == JobState.running)
                .values(**values)
            )
            return result.rowcount == 1

    # ---- logs -----------------------------------------------------------------------------------------

    def append_log(self, job_id: str, lines: Iterable[str]) -> None:
        now = utcnow()
        rows = [LogLine(job_id=job_id, line=line, created_at=now) for line in lines]
        if not rows:
            return
        with self._sessions.begin() as session:
            session.add_all(rows)

    def read_logs(self, job_id: str, offset: int, limit: int) -> Sequence[str]:
        with self._sessions() as session:
            query = (
                select(LogLine.line)
                .where(LogLine.job_id == job_id)
                .order_by(LogLine.id)
                .offset(offset)
                .limit(limit)
            )
            return list(session.scalars(query).all())


def new_job_id() -> str:
    return uuid4().hex
