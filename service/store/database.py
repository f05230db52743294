"""The job store's database: its engine (SQLite or PostgreSQL), the schema migrations, and the sessions
every table family of the store (service.store.*) works through."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import Engine
from sqlalchemy.orm import sessionmaker


def _make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 60})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
            # WAL lets the API read while job processes write; the busy timeout serialises writers.
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA busy_timeout=60000")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


def upgrade_database(engine: Engine) -> None:
    """Brings the schema to the newest migration; a database made before migrations existed (a `jobs`
    table, no `alembic_version`) is first stamped with the initial revision, so its jobs are kept.
    Processes starting together take turns (a file lock beside a SQLite file, an advisory lock on
    PostgreSQL), so a new database is created once."""
    from alembic import command
    from alembic.config import Config
    from filelock import FileLock
    from sqlalchemy import inspect

    config = Config()
    config.set_main_option("script_location", str(Path(__file__).parents[1] / "migrations"))
    database = engine.url.database if engine.dialect.name == "sqlite" else None
    with (
        FileLock(f"{database}.migrate.lock") if database else contextlib.nullcontext(),
        engine.begin() as connection,
    ):
        if engine.dialect.name == "postgresql":
            connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": MIGRATION_LOCK_KEY})
        config.attributes["connection"] = connection
        tables = inspect(connection).get_table_names()
        if "jobs" in tables and "alembic_version" not in tables:
            command.stamp(config, INITIAL_REVISION)
        command.upgrade(config, "head")


MIGRATION_LOCK_KEY = 0x5F4D4E52
"""PostgreSQL advisory lock held while one process migrates."""
INITIAL_REVISION = "0001"
"""The migration that creates the schema as it was before migrations (jobs and job_logs)."""


class Database:
    """A connection pool and its sessions; safe to use from several threads and processes.

    `migrate`: upgrade the schema first (the API and CLI do; job processes open an upgraded database).
    """

    def __init__(self, url: str, *, migrate: bool = True) -> None:
        if url.startswith("sqlite:///"):
            Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
        self.engine = _make_engine(url)
        if migrate:
            upgrade_database(self.engine)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def dispose(self) -> None:
        self.engine.dispose()

    def ping(self) -> None:
        """Raises when the database is unreachable."""
        with self.engine.connect() as connection:
            connection.execute(text("SELECT 1"))
