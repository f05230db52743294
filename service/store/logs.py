"""Job log lines: appended by jobs and the service, read by offset."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from sqlalchemy import select

from service.store.database import Database
from service.store.tables import LogLine, utcnow


class JobLogs(Database):
    """The `job_logs` table; a job's lines are ordered by id, and `offset` counts lines."""

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
