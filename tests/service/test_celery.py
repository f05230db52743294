"""The Celery executor against a real redis-server and a real Celery worker, both started here (loopback)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service import renders
from service.app import create_app
from service.celery_config import make_celery
from service.renders import RenderFailed, RenderQueue, RenderSpec, read_render_error, run_render_task
from service.settings import ServiceSettings
from tests.service.conftest import endless_nerf_upload, job_pid, make_settings, unity_hall_files, wait_for_job
from tests.service.servers import REDIS_SERVER, free_port, start_redis
from tests.service.test_job_machinery import CANCEL_DEADLINE_SECONDS, process_alive


@pytest.fixture(scope="module")
def broker_url(tmp_path_factory):
    if not Path(REDIS_SERVER).exists():
        pytest.fail("redis-server is not installed (apt-get install redis-server; scripts/test.sh does it)")
    server, url = start_redis(tmp_path_factory.mktemp("redis"))
    yield url
    server.terminate()
    server.wait(timeout=10)


def start_worker(env: dict[str, str], concurrency: int = 1, queues: str = "celery,renders"
                 ) -> subprocess.Popen:
    """A Celery worker process (prefork) with these SFMNERF_* settings, serving these queues (by default
    jobs and renders: one worker serves both here)."""
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "celery",
            "-A",
            "service.celery_app",
            "worker",
            "-Q",
            queues,
            "--pool",
            "prefork",
            "--concurrency",
            str(concurrency),
            "--loglevel",
            "warning",
            "--without-gossip",
            "--without-mingle",
            "-n",
            f"test-{os.getpid()}-{free_port()}@127.0.0.1",
        ],
        env={**os.environ, **env},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=Path(__file__).resolve().parents[2],
    )


def stop_worker(worker: subprocess.Popen) -> None:
    worker.send_signal(signal.SIGTERM)
    try:
        worker.wait(timeout=20)
    except subprocess.TimeoutExpired:
        worker.kill()
        worker.wait()


def worker_env(settings) -> dict[str, str]:
    return {
        "SFMNERF_EXECUTOR": "celery",
        "SFMNERF_BROKER_URL": settings.broker_url,
        "SFMNERF_DATA_DIR": str(settings.data_dir),
        "SFMNERF_HEARTBEAT_SECONDS": "0.5",
    }


@pytest.fixture(scope="module")
def celery_setup(tmp_path_factory, broker_url):
    """A Celery worker process (prefork, one job at a time) and an API, sharing database and data folder."""
    data_dir = tmp_path_factory.mktemp("celery") / "data"
    settings = make_settings(data_dir, executor="celery", broker_url=broker_url)
    with TestClient(create_app(settings)) as client:  # creates the database before the worker opens it
        worker = start_worker(worker_env(settings))
        try:
            yield client, worker
        finally:
            stop_worker(worker)


@pytest.fixture
def unity(shared_data):
    return unity_hall_files(shared_data / "unity_hall")


def started_in_worker(job: dict) -> bool:
    return job["state"] == "running" and job["stage"] not in (None, "starting")


def test_a_reconstruction_runs_on_a_celery_worker(celery_setup, unity):
    client, _ = celery_setup
    assert client.get("/readyz").json()["queue"] == "ok"
    job_id = client.post("/v1/reconstructions", files=unity).json()["id"]
    job = wait_for_job(client, job_id)
    assert job["state"] == "succeeded", client.get(f"/v1/jobs/{job_id}/logs").json()
    assert job["worker"].startswith("celery ")
    body = client.get(f"/v1/reconstructions/{job_id}").json()
    assert len(body["cameras"]) == job["result"]["registered_images"] >= 3
    assert client.get(f"/v1/reconstructions/{job_id}/points.ply").status_code == 200


def test_cancel_kills_the_celery_job_and_the_worker_goes_on(celery_setup, shared_data):
    client, worker = celery_setup
    job_id = client.post("/v1/nerf", **endless_nerf_upload(shared_data / "lego_tiny.npz")).json()["id"]
    wait_for_job(client, job_id, until=started_in_worker)
    pid = job_pid(client.app.state.settings.data_dir, job_id)
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 200
    job = wait_for_job(client, job_id, timeout=CANCEL_DEADLINE_SECONDS)
    assert job["state"] == "cancelled"
    deadline = time.monotonic() + CANCEL_DEADLINE_SECONDS
    while process_alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not process_alive(pid) and worker.poll() is None


def test_a_killed_celery_job_process_ends_failed_with_the_reason(celery_setup, shared_data):
    client, worker = celery_setup
    job_id = client.post("/v1/nerf", **endless_nerf_upload(shared_data / "lego_tiny.npz")).json()["id"]
    wait_for_job(client, job_id, until=started_in_worker)
    pid = job_pid(client.app.state.settings.data_dir, job_id)
    os.kill(pid, signal.SIGKILL)
    job = wait_for_job(client, job_id, timeout=90)  # the next process imports libraries first: slow when busy
    # The message comes back (task_reject_on_worker_lost); its next delivery records the end, runs nothing.
    assert job["state"] == "failed" and "worker process running it died" in job["error"], job
    assert job["attempt"] == 1 and worker.poll() is None


def test_the_broker_keeps_a_job_invisible_longer_than_the_longest_job_may_run():
    settings = ServiceSettings(max_runtime_nerf_minutes=600)
    conf = make_celery(settings).conf
    assert conf.broker_transport_options["visibility_timeout"] > 600 * 60
    assert conf.task_acks_late and conf.task_reject_on_worker_lost


def test_a_worker_process_may_take_minutes_to_start():
    """Celery kills a fresh process that is not up within 4 s by default; on a busy machine (CI) a process
    importing PyTorch took longer, and then no task ever ran."""
    assert make_celery(ServiceSettings()).conf.worker_proc_alive_timeout >= 60


def test_an_unexpected_render_error_is_answered_at_once_as_500_without_server_paths(tmp_path, monkeypatch):
    def crash(spec, cache_dir):
        raise RuntimeError(f"out of luck in {tmp_path}")

    monkeypatch.setattr(renders, "render_png", crash)
    spec = RenderSpec("job", str(tmp_path), "latest", 1, tuple(map(tuple, np.eye(4))), "data", 8, 8, None,
                      None)
    out_path, error_path = tmp_path / "view.png", tmp_path / "view.error"
    run_render_task(asdict(spec), str(out_path), str(error_path), None)
    answer = read_render_error(error_path)
    assert not out_path.exists() and answer.status_code == 500
    assert str(tmp_path) not in answer.detail and "log" in answer.detail


def test_a_celery_job_over_its_maximum_runtime_fails_with_the_reason(celery_setup, shared_data):
    client, worker = celery_setup
    short = client.app.state.settings.model_copy(update={"max_runtime_nerf_minutes": 0.07})
    with TestClient(create_app(short)) as limited:  # another API on the same database and broker
        # A million steps never end within the 4.2 s limit (a Unity Hall SIFT reconstruction, used before,
        # took 3.7 s on a fast machine and succeeded).
        job_id = limited.post("/v1/nerf", **endless_nerf_upload(shared_data / "lego_tiny.npz")).json()["id"]
        job = wait_for_job(limited, job_id)
    assert job["state"] == "failed" and "SFMNERF_MAX_RUNTIME_NERF_MINUTES" in job["error"], job
    assert worker.poll() is None


def test_a_message_redelivered_while_its_job_runs_never_runs_it_twice(tmp_path, broker_url, unity):
    """A visibility timeout (1 s) far below the job's duration: Redis hands the message to the worker's
    second process while the first runs the job; the job still runs once."""
    settings = make_settings(
        tmp_path / "data",
        executor="celery",
        broker_url=broker_url.rsplit("/", 1)[0] + "/1",  # its own queue: no other worker takes the task
        broker_visibility_timeout_seconds=1.0,
    )
    with TestClient(create_app(settings)) as client:
        worker = start_worker({**worker_env(settings), "SFMNERF_BROKER_VISIBILITY_TIMEOUT_SECONDS": "1"}, 2)
        try:
            job_id = client.post("/v1/reconstructions", files=unity).json()["id"]
            job = wait_for_job(client, job_id)
            lines = client.get(f"/v1/jobs/{job_id}/logs").json()["lines"]
        finally:
            stop_worker(worker)
    assert job["state"] == "succeeded" and job["attempt"] == 1, job
    assert sum(line.startswith("attempt ") for line in lines) == 1, lines
    assert any("second delivery of this job's task was ignored" in line for line in lines), lines


def test_a_render_goes_to_a_celery_worker_and_its_error_comes_back(celery_setup, tmp_path):
    """The Celery render path end to end (API -> broker -> worker -> shared folder -> API), with a run
    folder that has no checkpoint: the worker's message is the answer, without any server path."""
    client, _ = celery_setup
    settings = client.app.state.settings
    run_dir = settings.jobs_dir / "norun" / "output"
    run_dir.mkdir(parents=True)
    spec = RenderSpec("norun", str(run_dir), "latest", 1, tuple(map(tuple, np.eye(4))), "data", 8, 8, None,
                      None)
    with pytest.raises(RenderFailed) as failed:
        asyncio.run(RenderQueue(settings).render(spec))
    assert failed.value.status_code == 422 and failed.value.detail.startswith("checkpoint:")
    assert str(run_dir) not in failed.value.detail
