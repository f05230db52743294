"""The webhook outbox: a finished job's webhook marked due, claimed by one sender, delivered or failed
(service/webhooks.py sends them)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import select, update

from service.store.database import Database
from service.store.tables import Job, utcnow


class WebhookOutbox(Database):
    """pending -> sending (claimed at) -> delivered | failed, on the job's row."""

    def queue_webhook(self, job_id: str) -> None:
        """Marks a finished job's webhook (if it has a URL) for delivery by any live sender."""
        with self._sessions.begin() as session:
            session.execute(
                update(Job)
                .where(Job.id == job_id, Job.webhook_url.is_not(None))
                .values(webhook_state="pending", webhook_claimed_at=None)
            )

    def claim_webhook(self, stale_before: datetime) -> Job | None:
        """Takes one webhook to send: a pending one, or one whose sender claimed it before `stale_before`
        (that sender died). The conditional UPDATE makes each claim one sender's."""
        due = (Job.webhook_state == "pending") | (
            (Job.webhook_state == "sending") & (Job.webhook_claimed_at < stale_before)
        )
        with self._sessions.begin() as session:
            for job in session.scalars(select(Job).where(due).order_by(Job.finished_at).limit(8)).all():
                claimed = session.execute(
                    update(Job)
                    .where(Job.id == job.id, due)
                    .values(webhook_state="sending", webhook_claimed_at=utcnow())
                ).rowcount
                if claimed:
                    return job
        return None

    def finish_webhook(self, job_id: str, delivered: bool) -> None:
        with self._sessions.begin() as session:
            session.execute(
                update(Job)
                .where(Job.id == job_id)
                .values(webhook_state="delivered" if delivered else "failed", webhook_claimed_at=None)
            )
