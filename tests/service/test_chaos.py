"""Chaos: four clients submit scenes and jobs while the API is killed with kill -9 (its job processes too)
at random moments and restarted on the same data folder; nothing is lost, stuck or run twice.

At the end every scene and every job of the folder is in a terminal state, each attempt of a job ran once
(its log holds one start line per attempt), every file a succeeded job or scene lists is served, the folder
of an upload the API died during is removed at a later start, and the server's log and the job processes'
logs hold no traceback. The kill moments come from a seeded RNG."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
import signal
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import pytest

from service.kinds import TERMINAL_STATES
from service.layout import WORKER_LOG_NAME
from service.uploads import ORPHAN_MIN_AGE_SECONDS
from tests.service.conftest import TINY_MODEL_OPTIONS, tiny_nerf_npz, unity_hall_files
from tests.service.servers import free_port, start_server

SEED = 25
CLIENTS = 4
KILLS = 3
KILL_DELAY_SECONDS = (2.0, 15.0)
"""A kill comes this long (uniform) after the API answered ready."""
RUN_TIMEOUT_SECONDS = 600.0
REQUEST_TIMEOUT_SECONDS = 30.0
RETRY_SECONDS = 0.3
ADMIN = "chaos-admin-token-0123456789"
CLIENT_TOKENS = {f"client{i}": f"chaos-client{i}-token-0123456789" for i in range(CLIENTS)}
SERVER_SETTINGS = {
    "SFMNERF_API_TOKEN": ADMIN,
    "SFMNERF_CONCURRENCY": "2",
    "SFMNERF_JOB_THREADS": "1",
    "SFMNERF_HEARTBEAT_SECONDS": "0.5",
    "SFMNERF_MIN_FREE_DISK_BYTES": "0",
}
SCENE = {
    "steps": "10",
    "batch_rays": "256",
    "options": json.dumps({"checkpoint_every": 5, "val_every": 5, "log_every": 5}),
    "orbit_frames": "2",
    "orbit_max_side": "48",
    "held_out_max_side": "40",
}
NERF = {
    "model": "vanilla",
    "steps": "20",
    "batch_rays": "64",
    "device": "cpu",
    "options": json.dumps({"checkpoint_every": 5, "val_every": 10, "model_options": TINY_MODEL_OPTIONS}),
}
TRACEBACK = "Traceback (most recent call last)"


class Api:
    """The API on one port across restarts: requests retried while it is down, each loop bounded in time."""

    def __init__(self, port: int, token: str) -> None:
        self.client = httpx.Client(
            base_url=f"http://127.0.0.1:{port}",
            headers={"Authorization": f"Bearer {token}"},
            timeout=REQUEST_TIMEOUT_SECONDS,
        )

    def request(self, method: str, path: str, deadline: float, **kwargs) -> httpx.Response:
        """The first answer that is not a connection failure, a 503 (the API restarting) or a 429 (the
        upload checks busy: sent again after its Retry-After, as a client should)."""
        while True:
            pause = RETRY_SECONDS
            try:
                response = self.client.request(method, path, **kwargs)
                if response.status_code == 429:
                    pause = float(response.headers.get("Retry-After", RETRY_SECONDS))
                elif response.status_code != 503:
                    return response
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, f"{method} {path}: no answer before the deadline"
            time.sleep(pause)


class Submitter(threading.Thread):
    """One client: a scene, a reconstruction and a NeRF job, submitted while the API comes and goes.

    A submission the API died during is sent again (a client cannot know whether it arrived): the job
    the lost answer named, if any, is still found and checked at the end through the admin's listing."""

    def __init__(self, api: Api, shared_data: Path, deadline: float) -> None:
        super().__init__(daemon=True)
        self.api, self.deadline = api, deadline
        photos = unity_hall_files(shared_data / "unity_hall")
        dataset = tiny_nerf_npz(shared_data / "lego_tiny.npz")
        self.submissions = [
            ("scene", "/v1/scenes", {"files": photos, "data": SCENE}),
            ("job", "/v1/reconstructions", {"files": photos}),
            (
                "job",
                "/v1/nerf",
                {"files": {"dataset": ("tiny.npz", dataset, "application/zip")}, "data": NERF},
            ),
        ]
        self.created: list[tuple[str, str]] = []
        self.refused: list[str] = []

    def run(self) -> None:
        for what, path, body in self.submissions:
            response = self.api.request("POST", path, self.deadline, **body)
            if response.status_code == 202:
                self.created.append((what, response.json()["id"]))
            else:
                self.refused.append(f"POST {path}: {response.status_code} {response.text}")


def kill_api(server) -> None:
    """kill -9 of the API, then of every process it started (its process group), as a crash leaves it."""
    server.kill()
    server.wait(timeout=30)
    with contextlib.suppress(ProcessLookupError):  # its job processes may have died with it
        os.killpg(server.pid, signal.SIGKILL)


def all_done(admin: Api, deadline: float) -> tuple[list[dict], list[dict]]:
    """Every job and scene of the folder once none is queued or running (the admin sees them all)."""
    while True:
        jobs = admin.request("GET", "/v1/jobs", deadline, params={"limit": 500}).json()["items"]
        scenes = admin.request("GET", "/v1/scenes", deadline, params={"limit": 500}).json()["items"]
        if all(item["state"] in TERMINAL_STATES for item in jobs + scenes):
            return jobs, scenes
        stuck = [
            (item["id"], item["state"]) for item in jobs + scenes if item["state"] not in TERMINAL_STATES
        ]
        assert time.monotonic() < deadline, f"not terminal at the deadline: {stuck}"
        time.sleep(0.5)


def served_files(admin: Api, job: dict, deadline: float) -> list[str]:
    """The URLs of the files a succeeded job lists (its result route's downloads and checkpoints)."""
    if job["kind"] == "reconstruction":
        return list(
            admin.request("GET", f"/v1/reconstructions/{job['id']}", deadline).json()["files"].values()
        )
    if job["kind"] == "nerf":
        checkpoints = admin.request("GET", f"/v1/nerf/{job['id']}/checkpoints", deadline).json()
        return [f"/v1/nerf/{job['id']}"] + [checkpoint["url"] for checkpoint in checkpoints]
    if job["kind"] == "video":
        return [job["links"]["result"]]
    return []  # an evaluation's renders are listed by its scene


def scene_files(scene: dict) -> list[str]:
    """Every link of a succeeded scene but the render endpoint (a POST), and its held-out renders."""
    links = [url for name, url in scene["links"].items() if name != "render"]
    return links + [view["url"] for view in scene["held_out"]]


@pytest.mark.slow
def test_kill_9_of_the_api_at_random_moments_loses_no_job_and_runs_none_twice(tmp_path, shared_data):
    rng = random.Random(SEED)
    clients_file = tmp_path / "clients.txt"
    clients_file.write_text(
        "".join(
            f"{name}:sha256:{hashlib.sha256(token.encode()).hexdigest()}\n"
            for name, token in CLIENT_TOKENS.items()
        )
    )
    settings = {**SERVER_SETTINGS, "SFMNERF_CLIENTS_FILE": str(clients_file)}
    data_dir, port = tmp_path / "data", free_port()
    deadline = time.monotonic() + RUN_TIMEOUT_SECONDS
    server_log = tmp_path / "server.log"
    with open(server_log, "ab") as log:
        server = start_server(data_dir, port, settings=settings, log=log)
        admin = Api(port, ADMIN)
        submitters = [Submitter(Api(port, token), shared_data, deadline) for token in CLIENT_TOKENS.values()]
        try:
            for submitter in submitters:
                submitter.start()
            for _ in range(KILLS):
                time.sleep(rng.uniform(*KILL_DELAY_SECONDS))
                kill_api(server)
                server = start_server(data_dir, port, settings=settings, log=log)
            for submitter in submitters:
                submitter.join(timeout=max(0.0, deadline - time.monotonic()))
                assert not submitter.is_alive(), "a client's submissions did not end"
            jobs, scenes = all_done(admin, deadline)

            assert not [line for s in submitters for line in s.refused], [s.refused for s in submitters]
            created = Counter(what for s in submitters for what, _ in s.created)
            assert created == {"scene": CLIENTS, "job": 2 * CLIENTS}, created
            # Everything ends succeeded: a killed attempt is re-queued, never recorded as a failure.
            assert all(item["state"] == "succeeded" for item in jobs + scenes), [
                (item["id"], item["state"], item["error"]) for item in jobs + scenes
            ]
            # A scene's child jobs (those made from another job) are the ones its stages name: a restart
            # between creating a child and recording it in the scene would leave a second, unnamed one.
            children = {
                job_id for scene in scenes for stage in scene["stages"] for job_id in stage["job_ids"]
            }
            assert not [job["id"] for job in jobs if job["source_job_id"] and job["id"] not in children]
            requeued = 0
            for job in jobs:
                lines = admin.request("GET", f"/v1/jobs/{job['id']}/logs", deadline).json()["lines"]
                starts = Counter(
                    line.split()[1] for line in lines if line.startswith("attempt ") and " started " in line
                )
                assert all(count == 1 for count in starts.values()), (job["id"], lines)
                assert str(job["attempt"]) in starts and len(starts) <= job["attempt"], (job, lines)
                requeued += job["attempt"] > 1
            assert requeued, "no kill landed on a running job: the test exercised no restart"

            urls = [url for job in jobs for url in served_files(admin, job, deadline)]
            urls += [url for scene in scenes for url in scene_files(scene)]
            missing = [
                (url, r.status_code)
                for url in urls
                if (r := admin.request("GET", url, deadline)).status_code != 200 or not r.content
            ]
            assert not missing, missing
            # An upload the API died during left a folder without a job: the next start removes it once it
            # is older than any upload in progress (the age is faked here).
            stray = {path.name for path in (data_dir / "jobs").iterdir()} - {job["id"] for job in jobs}
            aged = time.time() - ORPHAN_MIN_AGE_SECONDS - 1
            for name in stray:
                os.utime(data_dir / "jobs" / name, (aged, aged))
            kill_api(server)
            server = start_server(data_dir, port, settings=settings, log=log)
            assert {path.name for path in (data_dir / "jobs").iterdir()} == {job["id"] for job in jobs}
        finally:
            kill_api(server)
    logs = {"server": server_log.read_text(errors="replace")}
    logs.update(
        {
            path.parent.name: path.read_text(errors="replace")
            for path in data_dir.glob(f"jobs/*/{WORKER_LOG_NAME}")
        }
    )
    assert not {name: text for name, text in logs.items() if TRACEBACK in text}, logs
