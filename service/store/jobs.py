"""Job rows and their state transitions: queued -> running (a fenced claim) -> succeeded | failed |
cancelled, re-queued after a restart. Every write a job process makes is fenced by the job's `attempt`
number, so a worker that lost its job (cancelled, re-queued after a restart) cannot overwrite the state its
successor writes."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, func, select, union, update

from service.fair_queue import fair_order
from service.kinds import TERMINAL_STATES, JobKind, JobState
from service.params import parse_params
from service.store.database import Database
from service.store.tables import SCENE_CHILD_COLUMNS, Job, LogLine, Scene, SceneChild, new_job_id, utcnow


class JobRows(Database):
    """The `jobs` table: creation, queries and state transitions."""

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
        scene_child: SceneChild | None = None,
    ) -> Job:
        """A queued job; with scene_child, recorded on its scene in the same transaction."""
        if scene_child is not None and scene_child.column not in {c.key for c in SCENE_CHILD_COLUMNS}:
            raise ValueError(f"{scene_child.column!r} is not a scene's child-job column")
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
            if scene_child is not None:
                scene = session.get(Scene, scene_child.scene_id, with_for_update=True)
                if scene is None:
                    raise LookupError(f"scene {scene_child.scene_id} does not exist")
                setattr(scene, scene_child.column, job.id)
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
