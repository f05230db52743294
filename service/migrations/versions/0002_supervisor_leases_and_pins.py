"""One owner per job (supervisor leases) and pinned jobs that never expire.

Revision ID: 0002
Revises: 0001
"""

import sqlalchemy as sa
from alembic import op

from service.store.tables import UTCDateTime

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "supervisors",
        sa.Column("id", sa.String(64), primary_key=True),
        sa.Column("host", sa.String(255), nullable=False),
        sa.Column("pid", sa.Integer, nullable=False),
        sa.Column("started_at", UTCDateTime, nullable=False),
        sa.Column("heartbeat_at", UTCDateTime, nullable=False),
    )
    # Plain ADD COLUMN (SQLite too): a batch rebuild of `jobs` would cascade-delete every job's log lines.
    op.add_column("jobs", sa.Column("supervisor_id", sa.String(64)))
    op.add_column("jobs", sa.Column("pinned", sa.Boolean, nullable=False, server_default=sa.false()))
    op.create_index("ix_jobs_supervisor_id", "jobs", ["supervisor_id"])


def downgrade() -> None:
    op.drop_index("ix_jobs_supervisor_id", "jobs")
    op.drop_column("jobs", "pinned")
    op.drop_column("jobs", "supervisor_id")
    op.drop_table("supervisors")
