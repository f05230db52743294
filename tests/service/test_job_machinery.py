"""Job processes under supervision: cancel, kill -9, retry, and a hard restart of the service.

The jobs are real Unity Hall reconstructions (a few seconds each), so every path here is the real one; a job
that must still be running when the test acts on it is an endless NeRF training job.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.executor import CeleryExecutor
from service.kinds import JobKind
from service.store import JobStore
from tests.service.conftest import endless_nerf_upload, job_pid, make_settings, unity_hall_files, wait_for_job
from tests.service.servers import free_port, start_server

CANCEL_DEADLINE_SECONDS = 5.0


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def started_working(job: dict) -> bool:
    """Running inside its process (past the imports: the reconstruction reported a stage)."""
    return job["state"] == "running" and job["stage"] not in (None, "starting")


@pytest.fixture
def unity(shared_data):
    return unity_hall_files(shared_data / "unity_hall")


def test_cancel_kills_the_running_job_and_marks_it_cancelled_within_seconds(client, settings, shared_data):
    job_id = client.post("/v1/nerf", **endless_nerf_upload(shared_data / "lego_tiny.npz")).json()["id"]
    running = wait_for_job(client, job_id, until=started_working)
    assert "pid" not in running["worker"]  # the API shows no PIDs
    pid = job_pid(settings.data_dir, job_id)
    asked = time.monotonic()
    response = client.post(f"/v1/jobs/{job_id}/cancel")
    assert response.status_code == 200
    job = wait_for_job(client, job_id, timeout=CANCEL_DEADLINE_SECONDS)
    assert time.monotonic() - asked < CANCEL_DEADLINE_SECONDS
    assert job["state"] == "cancelled" and job["error"] == "cancelled"
    assert not process_alive(pid)


def test_a_job_whose_process_is_killed_ends_failed_with_the_reason_and_can_be_retried(
    client, settings, unity
):
    job_id = client.post("/v1/reconstructions", files=unity).json()["id"]
    wait_for_job(client, job_id, until=started_working)
    pid = job_pid(settings.data_dir, job_id)
    os.kill(pid, signal.SIGKILL)
    job = wait_for_job(client, job_id, timeout=CANCEL_DEADLINE_SECONDS)
    assert job["state"] == "failed"
    assert "SIGKILL" in job["error"] and "died" in job["error"]
    assert client.get("/healthz").status_code == 200  # the API is untouched

    response = client.post(f"/v1/jobs/{job_id}/retry")
    assert response.status_code == 202 and response.headers["Location"].endswith(response.json()["id"])
    retry = wait_for_job(client, response.json()["id"])
    assert retry["state"] == "succeeded" and retry["retry_of"] == job_id
    assert client.get(f"/v1/reconstructions/{retry['id']}").json()["cameras"]


def test_a_job_over_its_maximum_runtime_is_stopped_and_fails_with_the_reason(tmp_path, unity):
    settings = make_settings(tmp_path / "data", max_runtime_reconstruction_minutes=0.01)
    with TestClient(create_app(settings)) as client:
        job_id = client.post("/v1/reconstructions", files=unity).json()["id"]
        store, deadline = client.app.state.store, time.monotonic() + 30
        while (pid := store.get(job_id).pid) is None:  # the pid is kept only while the job runs
            assert time.monotonic() < deadline, store.get(job_id).state
            time.sleep(0.02)
        job = wait_for_job(client, job_id, timeout=30)
    assert job["state"] == "failed" and "maximum runtime of 0.01 minutes" in job["error"], job
    assert "SFMNERF_MAX_RUNTIME_RECONSTRUCTION_MINUTES" in job["error"]
    assert not process_alive(pid)  # recorded once its process had exited


def test_a_hard_restart_of_the_service_loses_no_job(tmp_path, unity):
    """kill -9 of `sfmnerf serve` with one job running and one queued: after a restart both finish."""
    port = free_port()
    server = start_server(tmp_path / "data", port)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as client:
            first = client.post("/v1/reconstructions", files=unity).json()["id"]
            second = client.post("/v1/reconstructions", files=unity).json()["id"]
            wait_for_job(client, first, until=started_working)
            pid = job_pid(tmp_path / "data", first)
            assert client.get(f"/v1/jobs/{second}").json()["state"] == "queued"  # concurrency 1
            server.kill()
            server.wait()
            deadline = time.monotonic() + CANCEL_DEADLINE_SECONDS
            while process_alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
            assert not process_alive(pid), "the job process outlived its service"

            server = start_server(tmp_path / "data", port)
            jobs = [wait_for_job(client, job_id) for job_id in (first, second)]
            assert [job["state"] for job in jobs] == ["succeeded", "succeeded"]
            assert jobs[0]["attempt"] == 2 and jobs[1]["attempt"] == 1
            logs = client.get(f"/v1/jobs/{first}/logs").json()["lines"]
            assert any("re-queued" in line for line in logs)
    finally:
        server.kill()
        server.wait()


def test_a_celery_job_whose_worker_stops_heartbeating_is_marked_failed(tmp_path):
    """The API's reaper: a job claimed by a worker that then went silent ends failed, never stuck running."""
    settings = make_settings(
        tmp_path, executor="celery", heartbeat_seconds=0.1, heartbeat_timeout_seconds=0.5
    )
    store = JobStore(settings.resolved_database_url)
    job = store.create(JobKind.reconstruction, {})
    store.claim(job.id, worker="celery lost-host pid 1")
    executor = CeleryExecutor(settings, store)
    executor.start()
    try:
        deadline = time.monotonic() + 10
        while store.get(job.id).state == "running" and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        executor.stop()
    final = store.get(job.id)
    assert final.state == "failed" and "stopped sending heartbeats" in final.error
    assert "lost-host" in final.error


def test_a_job_the_pipeline_rejects_ends_failed_with_its_message(client, shared_data):
    """Two copies of one photo upload fine but have no parallax: the InputError's message is the error."""
    photo = (shared_data / "unity_hall" / "1.png").read_bytes()
    calibration = (shared_data / "unity_hall" / "calibration.txt").read_bytes()
    files = [
        ("images", ("1.png", photo, "image/png")),
        ("images", ("2.png", photo, "image/png")),
        ("calibration", ("calibration.txt", calibration, "text/plain")),
    ]
    job_id = client.post("/v1/reconstructions", files=files, data={"features": "sift"}).json()["id"]
    job = wait_for_job(client, job_id)
    assert job["state"] == "failed" and job["error"].startswith("no model could be started:"), job
    assert "1.png: best pair 1.png|2.png" in job["error"] and "panoramic" in job["error"]
    assert client.get(f"/v1/reconstructions/{job_id}").json()["cameras"] == []
    assert client.get(f"/v1/reconstructions/{job_id}/points.ply").status_code == 409
