"""Schema migrations (Alembic): a database made before migrations keeps its jobs; the models match."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from click.testing import CliRunner
from sqlalchemy import inspect

from service.cli import main
from service.kinds import JobKind, JobState
from service.store import Base, JobStore

# The job store's schema as `Base.metadata.create_all` made it before migrations (SQLite), verbatim.
PRE_MIGRATION_DDL = """
CREATE TABLE jobs (
    id VARCHAR(32) NOT NULL, kind VARCHAR(32) NOT NULL, state VARCHAR(16) NOT NULL, stage VARCHAR(200),
    progress FLOAT NOT NULL, created_at DATETIME NOT NULL, started_at DATETIME, finished_at DATETIME,
    heartbeat_at DATETIME, error TEXT, params JSON NOT NULL, result JSON, source_job_id VARCHAR(32),
    retry_of VARCHAR(32), webhook_url TEXT, attempt INTEGER NOT NULL, resume BOOLEAN NOT NULL,
    cancel_requested BOOLEAN NOT NULL, worker VARCHAR(200), pid INTEGER, task_id VARCHAR(100),
    PRIMARY KEY (id)
);
CREATE INDEX ix_jobs_state ON jobs (state);
CREATE INDEX ix_jobs_kind ON jobs (kind);
CREATE INDEX ix_jobs_source_job_id ON jobs (source_job_id);
CREATE INDEX ix_jobs_created_at ON jobs (created_at);
CREATE TABLE job_logs (
    id INTEGER NOT NULL, job_id VARCHAR(32) NOT NULL, created_at DATETIME NOT NULL, line TEXT NOT NULL,
    PRIMARY KEY (id), FOREIGN KEY(job_id) REFERENCES jobs (id) ON DELETE CASCADE
);
CREATE INDEX ix_job_logs_job_id ON job_logs (job_id);
INSERT INTO jobs VALUES ('a1', 'reconstruction', 'succeeded', 'done', 1.0, '2026-11-20 07:00:00.000000',
    '2026-11-20 07:00:01.000000', '2026-11-20 07:00:09.000000', '2026-11-20 07:00:09.000000', NULL,
    '{"config": {"features": "matches"}}', '{"points": 2810}', NULL, NULL, NULL, 1, 0, 0,
    'local pid 42', NULL, NULL);
INSERT INTO jobs VALUES ('b2', 'nerf', 'queued', NULL, 0.0, '2026-11-20 08:00:00.000000', NULL, NULL, NULL,
    NULL, '{"train_config": {"steps": 100}}', NULL, 'a1', NULL, NULL, 0, 0, 0, NULL, NULL, NULL);
INSERT INTO job_logs VALUES (1, 'a1', '2026-11-20 07:00:02.000000', 'stage: tracks (0%)');
"""


def old_database(path: Path) -> str:
    with sqlite3.connect(path) as connection:
        connection.executescript(PRE_MIGRATION_DDL)
    return f"sqlite:///{path}"


def test_a_database_from_before_migrations_is_upgraded_and_keeps_its_jobs(tmp_path):
    store = JobStore(old_database(tmp_path / "old.sqlite"))
    try:
        done, waiting = store.get("a1"), store.get("b2")
        assert (done.state, done.result, done.params) == (
            JobState.succeeded,
            {"points": 2810},
            {"config": {"features": "matches"}},
        )
        assert (waiting.state, waiting.source_job_id, waiting.pinned, waiting.owner) == (
            "queued",
            "a1",
            False,
            None,
        )
        assert store.read_logs("a1", 0, 10) == ["stage: tracks (0%)"]
        assert store.claim_next(5, "local", store.register_supervisor()) == [("b2", 1)]  # new columns work
        with store.engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    finally:
        store.dispose()


def test_the_migrations_build_exactly_the_models_schema_with_a_separate_owner_revision(tmp_path):
    store = JobStore(f"sqlite:///{tmp_path / 'new.sqlite'}")
    try:
        with store.engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
            assert MigrationContext.configure(connection).get_current_revision() == "0005"
            columns = {c["name"]: c for c in inspect(connection).get_columns("jobs")}
        assert columns["owner"]["nullable"] and {"supervisor_id", "pinned"} <= set(columns)
        video_defaults = {"num_frames": 36, "width": 200, "height": 200, "path": "captured"}
        assert store.create(JobKind.video, {}).params == video_defaults
    finally:
        store.dispose()


def test_sfmnerf_db_upgrade_migrates_the_configured_database(tmp_path, monkeypatch):
    url = old_database(tmp_path / "cli.sqlite")
    monkeypatch.setenv("SFMNERF_DATABASE_URL", url)
    result = CliRunner().invoke(main, ["db", "upgrade"])
    assert result.exit_code == 0, result.output
    with sqlite3.connect(tmp_path / "cli.sqlite") as connection:
        assert connection.execute("SELECT version_num FROM alembic_version").fetchone() == ("0005",)
        assert connection.execute("SELECT count(*) FROM jobs").fetchone() == (2,)


def test_processes_starting_together_on_a_new_database_create_it_once(tmp_path):
    url = f"sqlite:///{tmp_path / 'fresh.sqlite'}"
    code = f"from service.store import JobStore; JobStore({url!r}).dispose()"
    root = Path(__file__).resolve().parents[2]
    processes = [
        subprocess.Popen([sys.executable, "-c", code], cwd=root, stderr=subprocess.PIPE) for _ in range(4)
    ]
    errors = [p.communicate(timeout=120)[1].decode() for p in processes]
    assert [p.returncode for p in processes] == [0] * 4, errors
    with sqlite3.connect(tmp_path / "fresh.sqlite") as connection:
        assert connection.execute("SELECT version_num FROM alembic_version").fetchall() == [("0005",)]
