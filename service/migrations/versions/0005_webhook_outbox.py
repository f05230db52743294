"""Webhooks as a persistent outbox: a finished job's delivery state, so a restart loses none.

Revision ID: 0005
Revises: 0004
"""

import sqlalchemy as sa
from alembic import op

from service.store.tables import UTCDateTime

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database that main's `create_all` made (before migrations) may have the columns already.
    if "webhook_state" not in {c["name"] for c in sa.inspect(op.get_bind()).get_columns("jobs")}:
        op.add_column("jobs", sa.Column("webhook_state", sa.String(16), nullable=True))
        op.add_column("jobs", sa.Column("webhook_claimed_at", UTCDateTime, nullable=True))
        op.create_index("ix_jobs_webhook_state", "jobs", ["webhook_state"])


def downgrade() -> None:
    op.drop_index("ix_jobs_webhook_state", "jobs")
    op.drop_column("jobs", "webhook_claimed_at")
    op.drop_column("jobs", "webhook_state")
