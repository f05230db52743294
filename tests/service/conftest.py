"""Fixtures of the service tests: an app on a temporary data folder, Unity Hall uploads, job polling."""

from __future__ import annotations

import io
import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.kinds import TERMINAL_STATES
from service.settings import LOCAL_HOST_NAMES, ServiceSettings
from service.store import JobStore

JOB_TIMEOUT_SECONDS = 180.0
TINY_MODEL_OPTIONS = {
    "depth": 2,
    "width": 32,
    "colour_width": 16,
    "coarse_samples": 16,
    "fine_samples": 16,
    "position_bands": 4,
    "direction_bands": 2,
}
"""A vanilla NeRF small enough to train in seconds on the tiny dataset below."""


def tiny_nerf_npz(lego_tiny: Path, side: int = 20) -> bytes:
    """10 Lego views (8 train, 2 val) at side x side in tiny-NeRF .npz format: a NeRF trained in seconds."""
    source = np.load(lego_tiny)
    step = source["images"].shape[1] // side
    picked = np.r_[np.flatnonzero(source["split"] == 0)[:8], np.flatnonzero(source["split"] == 1)[:2]]
    buffer = io.BytesIO()
    np.savez(
        buffer,
        images=source["images"][picked][:, ::step, ::step],
        poses=source["poses"][picked],
        focal=float(source["focal"]) / step,
        split=np.r_[np.zeros(8, int), np.ones(2, int)],
    )
    return buffer.getvalue()


def endless_nerf_upload(lego_tiny: Path) -> dict:
    """A NeRF job on the tiny dataset with a million steps: it runs until it is cancelled or killed.

    A Unity Hall reconstruction ends in ~2 s, so a test that must catch a job while it works uses this.
    """
    return {
        "files": {"dataset": ("tiny.npz", tiny_nerf_npz(lego_tiny), "application/octet-stream")},
        "data": {
            "model": "vanilla",
            "steps": "1000000",
            "batch_rays": "64",
            "device": "cpu",
            "options": json.dumps({"model_options": TINY_MODEL_OPTIONS}),
        },
    }


class WebhookReceiver:
    """A loopback HTTP server answering every POST with `status` (and a Location), recording requests."""

    def __init__(self, status: int = 204, location: str | None = None) -> None:
        import http.server
        import threading

        outer = self
        self.requests: list[dict] = []

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802
                body = self.rfile.read(int(self.headers["Content-Length"]))
                outer.requests.append({"path": self.path, "host": self.headers["Host"], "body": body})
                self.send_response(status)
                if location:
                    self.send_header("Location", location)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/done"

    def bodies(self) -> list[dict]:
        return [json.loads(request["body"]) for request in self.requests]


def capture_reconstruction_config(monkeypatch: pytest.MonkeyPatch) -> list:
    """Replaces `estimation.reconstruct` by a stub that records the ReconstructionConfig it is given and
    stops with an InputError: what the CLI or a job passes on, without running anything."""
    import estimation

    seen: list = []

    def capture(images_dir, out_dir, config, progress=None, stages=None):
        seen.append(config)
        raise estimation.InputError("stopped after reading the configuration")

    monkeypatch.setattr(estimation, "reconstruct", capture)
    return seen


def make_settings(data_dir: Path, **overrides: object) -> ServiceSettings:
    """Settings for a test: a private data folder, quick heartbeats and webhook retries."""
    values: dict[str, object] = {
        "data_dir": data_dir,
        "heartbeat_seconds": 0.5,
        "webhook_backoff_seconds": 0.05,
        "webhook_attempts": 3,
        "webhook_poll_seconds": 0.1,
        "cancel_grace_seconds": 1.0,
        "trusted_hosts": ["testserver", *LOCAL_HOST_NAMES],  # TestClient's Host is "testserver"
    }
    values.update(overrides)
    return ServiceSettings(**values)


@pytest.fixture
def settings(tmp_path: Path) -> ServiceSettings:
    return make_settings(tmp_path / "data")


@pytest.fixture
def client(settings: ServiceSettings) -> Iterator[TestClient]:
    with TestClient(create_app(settings)) as test_client:
        yield test_client


def unity_hall_files(folder: Path, with_calibration: bool = True) -> list[tuple[str, tuple[str, bytes, str]]]:
    """The multipart `files` of a Unity Hall reconstruction upload."""
    files = [("images", (p.name, p.read_bytes(), "image/png")) for p in sorted(folder.glob("*.png"))]
    files += [
        ("matches", (p.name, p.read_bytes(), "text/plain")) for p in sorted(folder.glob("matching*.txt"))
    ]
    if with_calibration:
        files.append(
            ("calibration", ("calibration.txt", (folder / "calibration.txt").read_bytes(), "text/plain"))
        )
    return files


def wait_for_job(
    client: TestClient,
    job_id: str,
    states: frozenset[str] | set[str] = TERMINAL_STATES,
    timeout: float = JOB_TIMEOUT_SECONDS,
    until=None,
) -> dict:
    """Polls GET /v1/jobs/{id} until the job is in one of `states` (or `until(job)` holds)."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if until(job) if until else job["state"] in states:
            return job
        if time.monotonic() > deadline:
            logs = client.get(f"/v1/jobs/{job_id}/logs").json()
            raise AssertionError(f"job {job_id} still {job['state']} after {timeout} s: {job}\n{logs}")
        time.sleep(0.2)


def job_pid(data_dir: Path, job_id: str) -> int:
    """The pid of a job's process, read from the job store (the API shows no PIDs)."""
    store = JobStore(make_settings(data_dir).resolved_database_url)
    try:
        job = store.get(job_id)
    finally:
        store.dispose()
    assert job is not None and job.pid, job
    return job.pid
