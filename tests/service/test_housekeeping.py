"""Housekeeping: finished jobs expire with their files unless pinned; no new work on a full disk (507)."""

from __future__ import annotations

from datetime import timedelta
from uuid import uuid4

from fastapi.testclient import TestClient

from service.app import create_app
from service.housekeeping import expire_finished_jobs
from service.kinds import JobKind, JobState
from service.layout import job_dir
from service.params import parse_params
from service.store import Job, Scene, new_job_id, utcnow
from tests.service.conftest import make_settings


def finished_job(store, settings, age_minutes: float) -> str:
    """A succeeded job with a file, that ended `age_minutes` ago. Written ended in one transaction: the
    running service's supervisor claims a queued job within a poll and runs it (it did once, between a
    create and a claim here), and the run's end would then leave it neither old nor succeeded."""
    ended = utcnow() - timedelta(minutes=age_minutes)
    job = Job(id=new_job_id(), kind=str(JobKind.reconstruction), state=JobState.succeeded, attempt=1,
              params=parse_params(JobKind.reconstruction, {}).model_dump(mode="json"), result={},
              created_at=ended, started_at=ended, finished_at=ended)
    with store._sessions.begin() as session:
        session.add(job)
    (job_dir(settings, job.id) / "output").mkdir(parents=True)
    (job_dir(settings, job.id) / "output" / "points.ply").write_text("ply\n")
    return job.id


def test_finished_jobs_expire_with_their_files_unless_pinned(client, settings):
    store = client.app.state.store
    old, pinned, recent = (finished_job(store, settings, age) for age in (2881, 5000, 60))
    assert client.put(f"/v1/jobs/{pinned}/pin").json()["pinned"] is True
    running = store.create(JobKind.reconstruction, {}).id
    assert expire_finished_jobs(store, settings) == [old]
    assert client.get(f"/v1/jobs/{old}").status_code == 404 and not job_dir(settings, old).exists()
    for kept in (pinned, recent, running):
        assert client.get(f"/v1/jobs/{kept}").status_code == 200
    assert job_dir(settings, pinned).is_dir()

    assert client.delete(f"/v1/jobs/{pinned}/pin").json()["pinned"] is False
    assert expire_finished_jobs(store, settings) == [pinned]
    assert client.put("/v1/jobs/0123/pin").status_code == 404


def scene_of(store, jobs: list[str], state: JobState, age_minutes: float) -> str:
    """A scene whose reconstruction, NeRF and video child jobs are `jobs`, ended `age_minutes` ago."""
    scene = Scene(
        id=uuid4().hex, state=state, stage="views", finished_at=utcnow() - timedelta(minutes=age_minutes),
        reconstruction_job_id=jobs[0], nerf_job_id=jobs[1], video_job_id=jobs[2],
    )  # fmt: skip
    return store.create_scene(scene).id


def test_a_scenes_jobs_expire_only_with_the_whole_scene(client, settings):
    store = client.app.state.store
    running_scene_jobs = [finished_job(store, settings, 5000) for _ in range(3)]
    running = scene_of(store, running_scene_jobs, JobState.running, 5000)
    old_scene_jobs = [finished_job(store, settings, 5000) for _ in range(3)]
    old = scene_of(store, old_scene_jobs, JobState.succeeded, 5000)
    pinned_scene_jobs = [finished_job(store, settings, 5000) for _ in range(3)]
    pinned = scene_of(store, pinned_scene_jobs, JobState.failed, 5000)
    store.set_pinned(pinned_scene_jobs[1], True)
    recent = scene_of(store, [finished_job(store, settings, 5000) for _ in range(3)], JobState.succeeded, 60)

    assert sorted(expire_finished_jobs(store, settings)) == sorted(old_scene_jobs)
    assert client.get(f"/v1/scenes/{old}").status_code == 404
    assert not any(job_dir(settings, job_id).exists() for job_id in old_scene_jobs)
    for kept in (running, pinned, recent):
        assert client.get(f"/v1/scenes/{kept}").status_code == 200
    for job_id in running_scene_jobs + pinned_scene_jobs:
        assert client.get(f"/v1/jobs/{job_id}").status_code == 200 and job_dir(settings, job_id).is_dir()


def test_new_work_is_refused_with_507_when_the_disk_is_nearly_full(tmp_path, shared_data):
    settings = make_settings(tmp_path / "data", min_free_disk_bytes=2**62)
    photo = (shared_data / "unity_hall" / "1.png").read_bytes()
    with TestClient(create_app(settings)) as client:
        response = client.post("/v1/reconstructions", files=[("images", ("1.png", photo, "image/png"))])
        assert response.status_code == 507, response.text
        assert "SFMNERF_MIN_FREE_DISK_BYTES" in response.json()["detail"]
        assert str(settings.data_dir) not in response.text
        assert client.post("/v1/nerf", data={"reconstruction_id": "x"}).status_code == 507
        assert client.get("/v1/jobs").status_code == 200  # reading still works
        assert not list(settings.jobs_dir.iterdir())
