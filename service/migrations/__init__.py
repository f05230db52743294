"""Alembic migrations of the job store (applied by `service.db.upgrade_database`)."""
