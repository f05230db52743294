"""The job store's state machine and fencing, webhook delivery, and the upload safety helpers."""

from __future__ import annotations

import functools
import http.server
import io
import json
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import threading
import zipfile
from pathlib import Path

import pytest
from sqlalchemy import text

from service.kinds import JobKind, JobState
from service.settings import ServiceSettings
from service.store import Base, JobStore
from service.uploads import UploadRejected, extract_zip, inside, sanitize_filename
from service.webhooks import deliver
from tests.service.conftest import make_settings

POSTGRES_BIN_DIRS = [Path("/usr/lib/postgresql") / v / "bin" for v in ("17", "16", "15", "14")]


def _postgres_bin() -> Path | None:
    for folder in [*POSTGRES_BIN_DIRS, *(Path(p).parent for p in filter(None, [shutil.which("initdb")]))]:
        if (folder / "initdb").exists() and (folder / "pg_ctl").exists():
            return folder
    return None


@pytest.fixture(scope="module")
def postgres_url():
    """A throw-away PostgreSQL server on a loopback port (skipped where PostgreSQL or psycopg is missing)."""
    pytest.importorskip("psycopg", reason="the PostgreSQL driver (the `postgres` extra) is not installed")
    binaries = _postgres_bin()
    if binaries is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) are not installed")
    # Not under pytest's (root-only) temporary folder: the server user must reach it.
    folder = Path(tempfile.mkdtemp(prefix="sfmnerf-postgres-"))
    # PostgreSQL refuses to run as root: run it as nobody then.
    prefix = ["runuser", "-u", "nobody", "--"] if os.geteuid() == 0 else []
    if prefix:
        os.chown(folder, pwd.getpwnam("nobody").pw_uid, -1)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    run = functools.partial(subprocess.run, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run([*prefix, str(binaries / "initdb"), "-D", str(folder / "db"), "-U", "sfmnerf", "--auth=trust"])
    options = f"-p {port} -k {folder} -c listen_addresses=127.0.0.1"
    run([*prefix, str(binaries / "pg_ctl"), "-D", str(folder / "db"), "-o", options, "-w", "start"])
    try:
        yield f"postgresql+psycopg://sfmnerf@127.0.0.1:{port}/postgres"
    finally:
        run([*prefix, str(binaries / "pg_ctl"), "-D", str(folder / "db"), "-m", "immediate", "stop"])
        shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request, tmp_path: Path):
    """The job store on each supported database (a fresh schema per test)."""
    if request.param == "sqlite":
        store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
        yield store
    else:
        store = JobStore(request.getfixturevalue("postgres_url"))
        yield store
        Base.metadata.drop_all(store.engine)
        with store.engine.begin() as connection:  # the next test's store migrates from scratch
            connection.execute(text("DROP TABLE alembic_version"))
    store.dispose()


def test_a_job_is_claimed_once_and_each_claim_is_a_new_attempt(store):
    job = store.create(JobKind.reconstruction, {"config": {}})
    assert store.claim(job.id, "w1") == 1
    assert store.claim(job.id, "w2") is None
    assert store.get(job.id).state == JobState.running


def test_a_stale_attempt_cannot_write_after_the_job_was_requeued(store):
    job = store.create(JobKind.nerf, {})
    first = store.claim(job.id, "w1")
    assert store.requeue(job.id, first, resume=True)
    second = store.claim(job.id, "w2")
    assert second == first + 1
    assert not store.report_progress(job.id, first, "old", 0.9)
    assert not store.finish(job.id, first, JobState.succeeded)
    assert store.report_progress(job.id, second, "training", 0.5)
    assert store.finish(job.id, second, JobState.failed, error="boom")
    final = store.get(job.id)
    assert (final.state, final.error, final.stage, final.resume) == (
        JobState.failed,
        "boom",
        "training",
        True,
    )


def test_cancel_ends_a_queued_job_at_once_and_flags_a_running_one(store):
    queued = store.create(JobKind.reconstruction, {})
    assert store.request_cancel(queued.id).state == JobState.cancelled
    assert store.claim(queued.id, "w") is None
    running = store.create(JobKind.reconstruction, {})
    attempt = store.claim(running.id, "w")
    flagged = store.request_cancel(running.id)
    assert (flagged.state, flagged.cancel_requested) == (JobState.running, True)
    assert store.heartbeat(running.id, attempt) == (True, True)


def test_logs_are_read_from_an_offset_in_order(store):
    job = store.create(JobKind.reconstruction, {})
    store.append_log(job.id, [f"line {i}" for i in range(5)])
    assert store.read_logs(job.id, 3, 100) == ["line 3", "line 4"]
    assert store.read_logs(job.id, 5, 100) == []


def test_list_filters_by_kind_and_state_and_pages(store):
    ids = [store.create(JobKind.reconstruction, {}).id for _ in range(3)]
    store.create(JobKind.nerf, {})
    store.request_cancel(ids[0])
    rows, total = store.list(kind="reconstruction", limit=2)
    assert total == 3 and len(rows) == 2
    rows, total = store.list(state="cancelled")
    assert total == 1 and rows[0].id == ids[0]


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("1.png", "1.png"),
        ("../../etc/passwd", "passwd"),
        ("C:\\Users\\me\\photo 1.JPG", "photo_1.JPG"),
        ("/abs/path/x.png", "x.png"),
        ("we!rd$name.png", "we_rd_name.png"),
        ("..hidden.png", "hidden.png"),
    ],
)
def test_file_names_are_reduced_to_a_safe_last_component(name, expected):
    assert sanitize_filename(name, "images") == expected


@pytest.mark.parametrize("name", ["", "..", ".", "/", "a/.."])
def test_unusable_file_names_are_refused(name):
    with pytest.raises(UploadRejected) as error:
        sanitize_filename(name, "images")
    assert error.value.status_code == 422 and "images" in error.value.detail


def test_nothing_is_placed_outside_the_folder(tmp_path):
    with pytest.raises(UploadRejected):
        inside(tmp_path / "job", "../escape.txt")


def test_a_zip_whose_header_understates_its_size_is_stopped_while_extracting(tmp_path):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("data.bin", bytes(100_000))
    raw = bytearray(buffer.getvalue())
    # Patch the central directory's uncompressed size of the entry down to 10 bytes (a lying header).
    central = raw.rfind(b"PK\x01\x02")
    raw[central + 24 : central + 28] = (10).to_bytes(4, "little")
    archive = tmp_path / "lying.zip"
    archive.write_bytes(bytes(raw))
    with pytest.raises(UploadRejected) as error:
        extract_zip(archive, tmp_path / "out", ServiceSettings(data_dir=tmp_path))
    assert error.value.status_code in (413, 422) and "data.bin" in error.value.detail
    extracted = tmp_path / "out" / "data.bin"
    assert not extracted.exists() or extracted.stat().st_size <= 10 + (1 << 20)


class _FlakyReceiver(http.server.BaseHTTPRequestHandler):
    """Answers 500 to the first two POSTs, then 200; records the bodies."""

    bodies: list[dict] = []

    def do_POST(self) -> None:  # noqa: N802 (http.server's naming)
        body = self.rfile.read(int(self.headers["Content-Length"]))
        type(self).bodies.append(json.loads(body))
        self.send_response(500 if len(type(self).bodies) <= 2 else 200)
        self.end_headers()

    def log_message(self, *args: object) -> None:
        pass


def test_a_webhook_is_retried_with_back_off_until_it_is_accepted(tmp_path):
    _FlakyReceiver.bodies = []
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _FlakyReceiver)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/hook"
        settings = make_settings(
            tmp_path,
            webhook_attempts=4,
            webhook_backoff_seconds=0.01,
            webhook_allowed_networks=["127.0.0.0/8"],
        )
        assert deliver(url, json.dumps({"id": "x", "state": "succeeded"}), settings)
        assert len(_FlakyReceiver.bodies) == 3 and _FlakyReceiver.bodies[-1]["state"] == "succeeded"
        _FlakyReceiver.bodies = []
        assert not deliver(url, "{}", settings.model_copy(update={"webhook_attempts": 2}))
    finally:
        server.shutdown()
        server.server_close()
