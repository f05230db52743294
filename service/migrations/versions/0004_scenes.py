"""Scenes: photos to novel views as a chain of child jobs (service/scene_supervisor.py).

Revision ID: 0004
Revises: 0003
"""

import sqlalchemy as sa
from alembic import op

from service.store.tables import UTCDateTime

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # A database that main's `create_all` made (before migrations) may have the table already.
    if "scenes" in sa.inspect(op.get_bind()).get_table_names():
        return
    op.create_table(
        "scenes",
        sa.Column("id", sa.String(32), primary_key=True),
        sa.Column("state", sa.String(16), nullable=False, index=True),
        sa.Column("stage", sa.String(32), nullable=False),
        sa.Column("created_at", UTCDateTime, nullable=False, index=True),
        sa.Column("finished_at", UTCDateTime),
        sa.Column("error", sa.Text),
        sa.Column("params", sa.JSON, nullable=False),
        sa.Column("reconstruction_job_id", sa.String(32)),
        sa.Column("nerf_job_id", sa.String(32)),
        sa.Column("video_job_id", sa.String(32)),
        sa.Column("evaluation_job_id", sa.String(32)),
        sa.Column("log", sa.JSON, nullable=False),
    )


def downgrade() -> None:
    op.drop_table("scenes")
