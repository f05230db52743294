"""`sfmnerf db upgrade`: bring the job store's schema to the newest migration (the service does it too)."""

from __future__ import annotations

import click


@click.group()
def db() -> None:
    """The job store's database."""


@db.command()
def upgrade() -> None:
    """Apply the Alembic migrations to the database of SFMNERF_DATABASE_URL (or the data folder's SQLite)."""
    from service.settings import ServiceSettings
    from service.store.job_store import JobStore

    settings = ServiceSettings()
    store = JobStore(settings.resolved_database_url)
    store.dispose()
    click.echo(f"sfmnerf: database {settings.resolved_database_url.split('@')[-1]} is up to date")
