"""Alembic migrations of the job store (applied by `service.store.database.upgrade_database`)."""
