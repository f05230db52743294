"""The job store: jobs, their progress, results and log lines in a SQL database (SQLAlchemy 2).

SQLite (the default, a file in the data folder) and PostgreSQL both work. Several processes write to it:
the API, the local job processes and Celery workers. Every write a job process makes is fenced by the
job's `attempt` number, so a worker that lost its job (cancelled, re-queued after a restart) cannot
overwrite the state its successor writes. Each local supervisor (one per API process) holds a lease row
in `supervisors` that it refreshes; a running job names its supervisor, and only a job whose supervisor's
lease expired is taken over. The schema is created and upgraded by the Alembic migrations in
`service/migrations` (`upgrade_database`).
"""

from __future__ import annotations

import contextlib
import enum
import os
import socket
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path
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
    or_,
    select,
    text,
    union,
    update,
)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

from service.fair_queue import fair_order


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
    evaluation = "evaluation"


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


def upgrade_database(engine: Engine) -> None:
    """Brings the schema to the newest migration; a database made before migrations existed (a `jobs`
    table, no `alembic_version`) is first stamped with the initial revision, so its jobs are kept.
    Processes starting together take turns (a file lock beside a SQLite file, an advisory lock on
    PostgreSQL), so a new database is created once."""
    from alembic import command
    from alembic.config import Config
    from filelock import FileLock
    from sqlalchemy import inspect

    config = Config()
    config.set_main_option("script_location", str(Path(__file__).with_name("migrations")))
    database = engine.url.database if engine.dialect.name == "sqlite" else None
    with (
        FileLock(f"{database}.migrate.lock") if database else contextlib.nullcontext(),
        engine.begin() as connection,
    ):
        if engine.dialect.name == "postgresql":
            connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": MIGRATION_LOCK_KEY})
        config.attributes["connection"] = connection
        tables = inspect(connection).get_table_names()
        if "jobs" in tables and "alembic_version" not in tables:
            command.stamp(config, INITIAL_REVISION)
        command.upgrade(config, "head")


WEBHOOK_CANDIDATES = 200
"""Due webhooks looked at per claim (the oldest), so that every owner among them gets its turn."""
WEBHOOK_CLAIM_TRIES = 8
MIGRATION_LOCK_KEY = 0x5F4D4E52
"""PostgreSQL advisory lock held while one process migrates."""
INITIAL_REVISION = "0001"
"""The migration that creates the schema as it was before migrations (jobs and job_logs)."""


class JobStore:
    """All reads and writes of jobs and their logs; safe to use from several threads and processes.

    `migrate`: upgrade the schema first (the API and CLI do; job processes open an upgraded database).
    """

    def __init__(self, url: str, *, migrate: bool = True) -> None:
        if url.startswith("sqlite:///"):
            Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
        self.engine = _make_engine(url)
        if migrate:
            upgrade_database(self.engine)
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
        params: Any,
        *,
        job_id: str | None = None,
        source_job_id: str | None = None,
        retry_of: str | None = None,
        webhook_url: str | None = None,
        owner: str | None = None,
    ) -> Job:
        from service.params import parse_params

        job = Job(
            id=job_id or new_job_id(),
            kind=str(kind),
            state=JobState.queued,
            params=parse_params(kind, params).model_dump(mode="json"),
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

    def claim(
        self, job_id: str, worker: str, pid: int | None = None, supervisor_id: str | None = None
    ) -> int | None:
        """queued -> running for one worker; returns the new attempt number, None if not claimable.

        One conditional UPDATE: of several claimers (API processes, Celery deliveries) exactly one wins."""
        with self._sessions.begin() as session:
            return self._claim(session, job_id, worker, pid, supervisor_id)

    def claim_next(self, limit: int, worker: str, supervisor_id: str) -> list[tuple[str, int]]:
        """Claims up to `limit` queued jobs in turns across their owners (service.fair_queue), each
        owner's oldest first: [(job id, attempt)]. PostgreSQL skips rows another supervisor is claiming
        (FOR UPDATE SKIP LOCKED); on SQLite the conditional UPDATE decides."""
        with self._sessions.begin() as session:
            query = (
                select(Job.id, Job.owner)
                .where(Job.state == JobState.queued, Job.cancel_requested.is_(False))
                .order_by(Job.created_at)
                .with_for_update(skip_locked=True)
            )
            queued = [(job_id, owner) for job_id, owner in session.execute(query).all()]
            running_jobs = select(Job.owner, func.count()).where(Job.state == JobState.running)
            running = {o: int(n) for o, n in session.execute(running_jobs.group_by(Job.owner)).all()}
            claimed = []
            for job_id in fair_order(queued, running)[:limit]:
                attempt = self._claim(session, job_id, worker, None, supervisor_id)
                if attempt is not None:
                    claimed.append((job_id, attempt))
            return claimed

    @staticmethod
    def _claim(
        session: Any, job_id: str, worker: str, pid: int | None, supervisor_id: str | None
    ) -> int | None:
        now = utcnow()
        return session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == JobState.queued, Job.cancel_requested.is_(False))
            .values(
                state=JobState.running,
                attempt=Job.attempt + 1,
                started_at=now,
                heartbeat_at=now,
                finished_at=None,
                error=None,
                worker=worker,
                pid=pid,
                stage="starting",
                supervisor_id=supervisor_id,
            )
            .returning(Job.attempt)
        ).scalar_one_or_none()

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
            job_id,
            attempt,
            state=JobState.queued,
            resume=resume,
            pid=None,
            stage="re-queued",
            worker=None,
            supervisor_id=None,
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

    # ---- the webhook outbox ------------------------------------------------------------------------------
    def queue_webhook(self, job_id: str) -> None:
        """Marks a finished job's webhook (if it has a URL) for delivery by any live sender."""
        with self._sessions.begin() as session:
            session.execute(
                update(Job)
                .where(Job.id == job_id, Job.webhook_url.is_not(None))
                .values(webhook_state="pending", webhook_claimed_at=None)
            )

    def claim_webhook(self, stale_before: datetime, per_owner: int | None = None) -> Job | None:
        """Takes one webhook to send: a pending one, or one whose sender claimed it before `stale_before`
        (that sender died); in turns across owners (service.fair_queue), none of an owner with `per_owner`
        deliveries under way. The conditional UPDATE makes each claim one sender's."""
        due = (Job.webhook_state == "pending") | (
            (Job.webhook_state == "sending") & (Job.webhook_claimed_at < stale_before)
        )
        sending = (Job.webhook_state == "sending") & (Job.webhook_claimed_at >= stale_before)
        with self._sessions.begin() as session:
            under_way = session.execute(select(Job.owner, func.count()).where(sending).group_by(Job.owner))
            busy = {owner: int(count) for owner, count in under_way.all()}
            candidates = session.execute(
                select(Job.id, Job.owner).where(due).order_by(Job.finished_at).limit(WEBHOOK_CANDIDATES)
            ).all()
            allowed = [(i, o) for i, o in candidates if per_owner is None or busy.get(o, 0) < per_owner]
            for job_id in fair_order(allowed, busy)[:WEBHOOK_CLAIM_TRIES]:
                claimed = session.execute(
                    update(Job)
                    .where(Job.id == job_id, due)
                    .values(webhook_state="sending", webhook_claimed_at=utcnow())
                ).rowcount
                if claimed:
                    return session.get(Job, job_id)
        return None

    def finish_webhook(self, job_id: str, delivered: bool) -> None:
        with self._sessions.begin() as session:
            session.execute(
                update(Job)
                .where(Job.id == job_id)
                .values(webhook_state="delivered" if delivered else "failed", webhook_claimed_at=None)
            )

    def cancel_requested_running(self, supervisor_id: str) -> list[Job]:
        """Running jobs of this supervisor that a client (on any API process) asked to cancel."""
        with self._sessions() as session:
            query = select(Job).where(
                Job.state == JobState.running,
                Job.cancel_requested.is_(True),
                Job.supervisor_id == supervisor_id,
            )
            return list(session.scalars(query).all())

    def running_longer_than(self, kind: str, seconds: float, supervisor_id: str | None = None) -> list[Job]:
        """Running jobs of a kind started more than `seconds` ago (of one supervisor when given)."""
        query = select(Job).where(
            Job.state == JobState.running,
            Job.kind == kind,
            Job.started_at < utcnow() - timedelta(seconds=seconds),
        )
        if supervisor_id is not None:
            query = query.where(Job.supervisor_id == supervisor_id)
        with self._sessions() as session:
            return list(session.scalars(query).all())

    def set_pinned(self, job_id: str, pinned: bool) -> Job | None:
        with self._sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is not None:
                job.pinned = pinned
            return job

    def expired(self, finished_before: datetime, limit: int = 100) -> list[str]:
        """Finished, unpinned jobs that ended before the cut-off, oldest first; a scene's child jobs are
        left to their scene, which expires as a whole (`expired_scenes`)."""
        scene_children = union(
            *(select(column).where(column.is_not(None)) for column in SCENE_CHILD_COLUMNS)
        )
        with self._sessions() as session:
            query = (
                select(Job.id)
                .where(
                    Job.state.in_(list(TERMINAL_STATES)),
                    Job.pinned.is_(False),
                    Job.finished_at < finished_before,
                    Job.id.not_in(scene_children),
                )
                .order_by(Job.finished_at)
                .limit(limit)
            )
            return list(session.scalars(query).all())

    # ---- supervisor leases ----------------------------------------------------------------------------

    def register_supervisor(self) -> str:
        """A new lease for this process; returns its id."""
        supervisor = Supervisor(id=uuid4().hex, host=socket.gethostname(), pid=os.getpid())
        with self._sessions.begin() as session:
            session.add(supervisor)
        return supervisor.id

    def renew_lease(self, supervisor_id: str) -> None:
        with self._sessions.begin() as session:
            session.execute(
                update(Supervisor).where(Supervisor.id == supervisor_id).values(heartbeat_at=utcnow())
            )

    def release_lease(self, supervisor_id: str) -> None:
        with self._sessions.begin() as session:
            session.execute(delete(Supervisor).where(Supervisor.id == supervisor_id))

    def orphaned_running(self, lease_timeout: timedelta) -> list[Job]:
        """Running local jobs whose supervisor is gone: no lease row, a lease not renewed within
        `lease_timeout`, or a lease of a process on this host that no longer exists (killed just now)."""
        with self._sessions() as session:
            leases = {s.id: s for s in session.scalars(select(Supervisor)).all()}
            query = select(Job).where(
                Job.state == JobState.running,
                or_(Job.supervisor_id.is_not(None), Job.worker.like("local%")),
            )
            jobs = list(session.scalars(query).all())
        cutoff = utcnow() - lease_timeout
        host = socket.gethostname()

        def alive(lease: Supervisor | None) -> bool:
            if lease is None or lease.heartbeat_at < cutoff:
                return False
            return lease.host != host or process_exists(lease.pid)

        return [job for job in jobs if not alive(leases.get(job.supervisor_id or ""))]

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

    # ---- scenes ---------------------------------------------------------------------------------------

    def create_scene(self, scene: Scene) -> Scene:
        with self._sessions.begin() as session:
            session.add(scene)
        return scene

    def get_scene(self, scene_id: str) -> Scene | None:
        with self._sessions() as session:
            return session.get(Scene, scene_id)

    def list_scenes(
        self, *, state: str | None = None, owner: str | None = None, limit: int = 50, offset: int = 0
    ) -> tuple[list[Scene], int]:
        """Scenes newest first; only `owner`'s (the owner of their reconstruction job) when given."""
        query = select(Scene) if state is None else select(Scene).where(Scene.state == state)
        if owner is not None:
            query = query.join(Job, Job.id == Scene.reconstruction_job_id).where(Job.owner == owner)
        with self._sessions() as session:
            total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
            rows = session.scalars(
                query.order_by(Scene.created_at.desc(), Scene.id).limit(limit).offset(offset)
            ).all()
        return list(rows), int(total)

    def update_scene(self, scene_id: str, *, log: str | None = None, **values: Any) -> Scene | None:
        """Sets the fields given and appends `log` to the scene's own log lines; the scene after."""
        with self._sessions.begin() as session:
            scene = session.get(Scene, scene_id, with_for_update=True)
            if scene is None:
                return None
            for name, value in values.items():
                setattr(scene, name, value)
            if log is not None:
                scene.log = [*scene.log, f"{utcnow():%Y-%m-%d %H:%M:%S} {log}"]
            return scene

    def expired_scenes(self, finished_before: datetime, limit: int = 100) -> list[Scene]:
        """Finished scenes that ended before the cut-off, oldest first, whose child jobs have all ended and
        none is pinned (pinning any child job keeps its whole scene)."""
        with self._sessions() as session:
            query = (
                select(Scene)
                .where(Scene.state.in_(list(TERMINAL_STATES)), Scene.finished_at < finished_before)
                .order_by(Scene.finished_at)
                .limit(limit)
            )
            scenes = list(session.scalars(query).all())
        return [
            scene
            for scene in scenes
            if all(
                job.state in TERMINAL_STATES and not job.pinned
                for job in map(self.get, self.scene_job_ids(scene))
                if job is not None
            )
        ]

    def scene_job_ids(self, scene: Scene) -> list[str]:
        """A scene's child jobs and the jobs they retried, last stage first (the order to delete them)."""
        ids = []
        for column in reversed(SCENE_CHILD_COLUMNS):
            job_id = getattr(scene, column.key)
            while job_id and (job := self.get(job_id)) is not None:
                ids.append(job_id)
                job_id = job.retry_of
        return ids

    def delete_scene(self, scene_id: str) -> bool:
        with self._sessions.begin() as session:
            return session.execute(delete(Scene).where(Scene.id == scene_id)).rowcount == 1

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


def process_exists(pid: int) -> bool:
    """Whether a process of this host has this pid (a zombie, exited but not yet reaped, counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:  # no /proc: the signal test is all there is
        return True
