"""Two `sfmnerf serve` processes on one data folder (one SQLite database): one owner per job.

Each server's supervisor claims jobs under its own lease; neither re-queues nor kills the other's jobs,
and a cancel sent to either reaches the job's owner.
"""

from __future__ import annotations

import httpx
import pytest

from tests.service.conftest import endless_nerf_upload, job_pid, wait_for_job
from tests.service.servers import free_port, start_server
from tests.service.test_job_machinery import process_alive, started_working

JOBS = 8


def quick_failing_upload(unity_hall):
    """Two copies of one photo: the job process starts, finds no parallax and ends failed within seconds."""
    photo = (unity_hall / "1.png").read_bytes()
    return {
        "files": [
            ("images", ("1.png", photo, "image/png")),
            ("images", ("2.png", photo, "image/png")),
            ("calibration", ("calibration.txt", (unity_hall / "calibration.txt").read_bytes(), "text/plain")),
        ],
        "data": {"features": "sift"},
    }


@pytest.mark.slow
def test_two_servers_on_one_folder_run_each_job_exactly_once_and_kill_none(tmp_path, shared_data):
    # A job that runs until it is stopped: a reconstruction (~2 s) could end before it is seen working.
    endless = endless_nerf_upload(shared_data / "lego_tiny.npz")
    quick = quick_failing_upload(shared_data / "unity_hall")
    first_port = free_port()
    # Two job slots: the first server keeps claiming beside the endless job, so both servers compete.
    first = start_server(tmp_path / "data", first_port, settings={"SFMNERF_CONCURRENCY": "2"})
    second = None
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{first_port}", timeout=30) as a:
            ids = [a.post("/v1/nerf", **endless).json()["id"]]
            ids += [a.post("/v1/reconstructions", **quick).json()["id"] for _ in range(JOBS - 1)]
            wait_for_job(a, ids[0], until=started_working)
            first_pid = job_pid(tmp_path / "data", ids[0])
            # A second server starting on the same folder used to kill this worker and re-run its job.
            second_port = free_port()
            second = start_server(tmp_path / "data", second_port)
            with httpx.Client(base_url=f"http://127.0.0.1:{second_port}", timeout=30) as b:
                assert process_alive(first_pid)
                quick_jobs = [wait_for_job(a if i % 2 else b, job_id) for i, job_id in enumerate(ids[1:])]
                assert all(job["state"] == "failed" and job["error"] for job in quick_jobs), quick_jobs
                # The endless job kept its one process while the other server ran the rest.
                assert b.get(f"/v1/jobs/{ids[0]}").json()["state"] == "running"
                assert process_alive(first_pid) and job_pid(tmp_path / "data", ids[0]) == first_pid

                # Cancel on the server that may not own the job: the owner stops it, and `cancelled`
                # is recorded once its process has exited.
                ids.append(a.post("/v1/nerf", **endless).json()["id"])
                wait_for_job(b, ids[-1], until=started_working)
                for job_id, pid in ((ids[0], first_pid), (ids[-1], job_pid(tmp_path / "data", ids[-1]))):
                    assert b.post(f"/v1/jobs/{job_id}/cancel").status_code == 200
                    assert wait_for_job(b, job_id, timeout=10)["state"] == "cancelled"
                    assert not process_alive(pid)
                for job_id in ids:
                    assert b.get(f"/v1/jobs/{job_id}").json()["attempt"] == 1
                    lines = b.get(f"/v1/jobs/{job_id}/logs").json()["lines"]
                    assert sum(line.startswith("attempt ") for line in lines) == 1, lines
                    assert not any("re-queued" in line for line in lines), lines
    finally:
        for server in (first, second):
            if server is not None:
                server.kill()
                server.wait()
