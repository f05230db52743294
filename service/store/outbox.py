"""The webhook outbox: a finished job's webhook marked due, claimed by one sender, delivered or failed
(service/webhooks.py sends them)."""

from __future__ import annotations

from datetime import datetime

from sqlalchemy import func, select, update

from service.fair_queue import fair_order
from service.store.database import Database
from service.store.tables import Job, utcnow

WEBHOOK_CANDIDATES = 200
"""Due webhooks looked at per claim (the oldest), so that every owner among them gets its turn."""
WEBHOOK_CLAIM_TRIES = 8


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
