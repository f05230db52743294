"""The API's helper processes end with it: validation, render and job processes die when the API is
killed, and a new API on the same data folder ends any recorded process a killed one left behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.child_processes import PROCESSES_DIR, start_time
from service.settings import WORKER_SETTINGS_ENV
from tests.service.conftest import TINY_MODEL_OPTIONS, make_settings, tiny_nerf_npz
from tests.service.servers import ROOT, descendants, free_port, start_server

GONE_SECONDS = 10.0


def running(pid: int) -> bool:
    return start_time(pid) is not None


def wait_gone(pids: list[int]) -> list[int]:
    """The pids still running after GONE_SECONDS."""
    deadline = time.monotonic() + GONE_SECONDS
    while time.monotonic() < deadline and any(running(pid) for pid in pids):
        time.sleep(0.1)
    return [pid for pid in pids if running(pid)]


def test_a_validation_process_dies_with_its_killed_parent(tmp_path):
    """A parent starts a check (which waits for its arguments on stdin) and is killed with SIGKILL."""
    settings = make_settings(tmp_path / "data")
    parent_code = (
        "import os, subprocess, sys, time\n"
        "child = subprocess.Popen([sys.executable, '-m', 'service.validation', 'dataset', str(os.getpid())],"
        " stdin=subprocess.PIPE)\n"
        "print(child.pid, flush=True)\n"
        "time.sleep(120)\n"
    )
    env = {**os.environ, WORKER_SETTINGS_ENV: settings.to_worker_json(), "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen([sys.executable, "-c", parent_code], stdout=subprocess.PIPE, env=env, cwd=ROOT)
    child = int(parent.stdout.readline())
    record = tmp_path / "data" / PROCESSES_DIR / str(parent.pid) / str(child)
    deadline = time.monotonic() + GONE_SECONDS
    while not record.is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert record.read_text() == start_time(child)  # its pid file, for a later start-up to reap
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    assert wait_gone([child]) == []


def test_leftovers_of_a_killed_api_are_ended_at_start_up_and_nothing_else(tmp_path):
    settings = make_settings(tmp_path / "data")
    gone_api = subprocess.Popen(["true"])
    gone_api.wait()
    leftover = subprocess.Popen(["sleep", "300"])
    reused = subprocess.Popen(["sleep", "300"])  # a pid given to another program since: other start time
    other_api = subprocess.Popen(["sleep", "300"])  # an API still running on the same data folder
    try:
        folder = settings.data_dir / PROCESSES_DIR / str(gone_api.pid)
        folder.mkdir(parents=True)
        (folder / str(leftover.pid)).write_text(start_time(leftover.pid))
        (folder / str(reused.pid)).write_text(str(int(start_time(reused.pid)) - 1))
        alive = settings.data_dir / PROCESSES_DIR / str(other_api.pid)
        alive.mkdir()
        (alive / str(reused.pid)).write_text(start_time(reused.pid))
        with TestClient(create_app(settings)):
            assert leftover.wait(timeout=GONE_SECONDS) == -signal.SIGKILL
            assert reused.poll() is None
            assert not folder.exists() and alive.is_dir()
    finally:
        for process in (leftover, reused, other_api):
            process.kill()
            process.wait()


@pytest.mark.slow
def test_render_and_job_processes_die_with_a_killed_api(tmp_path, shared_data):
    """A real server trains a NeRF (a job process) and renders a view (a render process and its resource
    tracker); after kill -9 of the API none of its descendants is left."""
    port = free_port()
    server = start_server(tmp_path / "data", port)
    try:
        base = f"http://127.0.0.1:{port}"
        options = {"model_options": TINY_MODEL_OPTIONS, "checkpoint_every": 2}
        data = {"model": "vanilla", "steps": "1000000", "batch_rays": "64", "device": "cpu",
                "options": json.dumps(options)}  # fmt: skip
        files = {"dataset": ("tiny.npz", tiny_nerf_npz(shared_data / "lego_tiny.npz"), "application/x-npz")}
        job_id = httpx.post(f"{base}/v1/nerf", files=files, data=data, timeout=120).json()["id"]
        render = {"c2w": np.eye(4).tolist(), "width": 8, "height": 8}
        url = f"{base}/v1/nerf/{job_id}/render"
        deadline = time.monotonic() + 300
        while (answer := httpx.post(url, json=render, timeout=120)).status_code == 409:  # no checkpoint yet
            assert time.monotonic() < deadline, "no checkpoint within 300 s"
            time.sleep(0.5)
        assert answer.status_code == 200
        children = descendants(server.pid)
        assert len(children) >= 2  # the job process and the render process at least
    finally:
        server.send_signal(signal.SIGKILL)
        server.wait()
    assert wait_gone(children) == []
