"""Supervisor leases: each local supervisor (one per API process) holds a row it renews; a running job
names its supervisor, and only a job whose supervisor's lease lapsed (or whose process is gone) is taken
over."""

from __future__ import annotations

import os
import socket
from datetime import timedelta
from uuid import uuid4

from sqlalchemy import delete, or_, select, update

from service.kinds import JobState
from service.store.database import Database
from service.store.tables import Job, Supervisor, utcnow


class SupervisorLeases(Database):
    """The `supervisors` table and the running jobs whose supervisor is gone."""

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
