"""Scenes: one request from photos to novel views (reconstruction -> NeRF -> orbit and held-out renders),
its progress and links, failure at the stage that failed, cancel, retry from that stage, delete; and the
`sfmnerf scene` command doing the same in one process."""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import time
import zipfile
from pathlib import Path

import pytest
from click.testing import CliRunner
from fastapi.testclient import TestClient
from PIL import Image

from service.app import create_app
from service.cli import main as cli
from service.pipeline import orbit_size, registration_problem
from tests.service.conftest import JOB_TIMEOUT_SECONDS, make_settings, unity_hall_files

ALICE, BOB, ADMIN = "alice-token-0123456789", "bob-token-0123456789", "admin-token-0123456789"

QUICK_NERF = {
    "steps": "10",
    "batch_rays": "256",
    "options": json.dumps({"checkpoint_every": 10, "val_every": 10, "log_every": 5}),
    "orbit_frames": "2",
    "orbit_max_side": "48",
    "held_out_max_side": "40",
}


def wait_for_scene(
    client: TestClient, scene_id: str, until=None, timeout: float = 2 * JOB_TIMEOUT_SECONDS
) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        scene = client.get(f"/v1/scenes/{scene_id}").json()
        if until(scene) if until else scene["state"] != "running":
            return scene
        assert time.monotonic() < deadline, f"scene {scene_id} still {scene['state']}: {scene}"
        time.sleep(0.3)


class ServerLog(logging.Handler):
    """The server's log records while a module's scene runs (its threads log to the root logger)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(self.format(record))


@pytest.fixture(scope="module")
def server_log() -> ServerLog:
    """Filled by `finished` while its scene runs."""
    return ServerLog()


@pytest.fixture(scope="module")
def finished(tmp_path_factory, shared_data, server_log):
    """One Unity Hall scene run to its end, created by client alice: (client as alice, scene, settings)."""
    folder = tmp_path_factory.mktemp("scenes")
    clients_file = folder / "clients.txt"
    clients_file.write_text(
        "".join(
            f"{name}:sha256:{hashlib.sha256(token.encode()).hexdigest()}\n"
            for name, token in [("alice", ALICE), ("bob", BOB)]
        )
    )
    settings = make_settings(folder / "data", job_threads=1, api_token=ADMIN, clients_file=clients_file)
    logging.getLogger().addHandler(server_log)
    try:
        with TestClient(create_app(settings), headers={"Authorization": f"Bearer {ALICE}"}) as client:
            response = client.post(
                "/v1/scenes", files=unity_hall_files(shared_data / "unity_hall"), data=QUICK_NERF
            )
            assert response.status_code == 202, response.text
            assert response.headers["Location"] == f"/v1/scenes/{response.json()['id']}"
            scene = wait_for_scene(client, response.json()["id"])
            logging.getLogger().removeHandler(server_log)
            yield client, scene, settings
    finally:
        logging.getLogger().removeHandler(server_log)


@pytest.mark.slow
def test_a_scene_goes_from_photos_to_novel_views(finished):
    client, scene, _ = finished
    assert scene["state"] == "succeeded" and scene["stage"] == "done", scene
    assert scene["progress"] == pytest.approx(1.0)
    assert [(s["name"], s["state"]) for s in scene["stages"]] == [
        ("reconstruction", "succeeded"), ("nerf", "succeeded"), ("views", "succeeded")
    ]  # fmt: skip
    assert [len(s["job_ids"]) for s in scene["stages"]] == [1, 1, 2]
    assert any("registered 5 of 5 images" in line for line in scene["log"])


@pytest.mark.slow
def test_a_scene_run_through_the_supervisors_leaves_a_server_log_without_a_traceback(finished, server_log):
    _, scene, _ = finished
    assert scene["state"] == "succeeded", scene
    assert not [line for line in server_log.lines if "Traceback" in line or line.startswith("ERROR")], (
        server_log.lines
    )


@pytest.mark.slow
def test_every_artifact_of_both_stages_is_linked_and_served(finished):
    client, scene, _ = finished
    links = scene["links"]
    assert client.get(links["points.ply"]).content.startswith(b"ply\n")
    assert len(client.get(links["reconstruction"]).json()["cameras"]) == 5
    assert client.get(links["nerf"]).json()["latest_step"] == 10
    gif = Image.open(io.BytesIO(client.get(links["video"]).content))
    assert gif.n_frames == 2 and gif.size == orbit_size(800, 600, 48)
    assert client.get(links["validation"]).headers["content-type"] == "image/png"
    for name in ("reconstruction_logs", "nerf_logs", "video_logs", "evaluation_logs"):
        assert client.get(links[name]).json()["lines"], name


@pytest.mark.slow
def test_held_out_views_are_rendered_and_scored(finished):
    client, scene, _ = finished
    # Unity Hall has 5 photos, fewer than the holdout interval: the views scored are the training views.
    assert [view["image"] for view in scene["held_out"]] == ["1"]  # LLFF held-out frames 0, 8, ... of 5
    assert all(math.isfinite(view["psnr"]) and 0 <= view["ssim"] <= 1 for view in scene["held_out"])
    render = client.get(scene["held_out"][0]["url"])
    assert Image.open(io.BytesIO(render.content)).size == (800 // 20, 600 // 20)
    assert client.get(f"/v1/scenes/{scene['id']}/held-out/..%2Fmetrics.json").status_code == 404


@pytest.mark.slow
def test_a_scene_and_its_child_jobs_belong_to_the_client_that_created_it(finished):
    client, scene, _ = finished
    store = client.app.state.store
    child_ids = [job_id for stage in scene["stages"] for job_id in stage["job_ids"]]
    assert len(child_ids) == 4 and {store.get(job_id).owner for job_id in child_ids} == {"alice"}
    bob = {"Authorization": f"Bearer {BOB}"}
    for method, path in [
        ("get", ""), ("post", "/cancel"), ("post", "/retry"), ("delete", ""), ("get", "/held-out/1.png")
    ]:  # fmt: skip
        response = client.request(method, f"/v1/scenes/{scene['id']}{path}", headers=bob)
        assert response.status_code == 404, (method, path, response.text)
        assert response.json()["detail"] == f"scene {scene['id']} not found"
    assert client.get("/v1/scenes", headers=bob).json()["total"] == 0
    assert client.get(f"/v1/scenes/{scene['id']}", headers={"Authorization": f"Bearer {ADMIN}"}).is_success


def test_scenes_are_listed_newest_first(finished):
    client, scene, _ = finished
    listed = client.get("/v1/scenes").json()
    assert listed["total"] >= 1 and listed["items"][0]["id"] == scene["id"]
    assert client.get("/v1/scenes/0123456789abcdef").status_code == 404


@pytest.mark.slow
def test_too_few_registered_images_fail_the_scene_at_the_reconstruction_and_keep_it(client, shared_data):
    hall = shared_data / "unity_hall"
    files = [("images", (name, (hall / name).read_bytes(), "image/png")) for name in ("1.png", "2.png")]
    files.append(("calibration", ("calibration.txt", (hall / "calibration.txt").read_bytes(), "text/plain")))
    response = client.post("/v1/scenes", files=files, data={"features": "sift"})
    assert response.status_code == 202, response.text
    scene = wait_for_scene(client, response.json()["id"])
    assert scene["state"] == "failed" and scene["stage"] == "reconstruction"
    assert "registered 2 of 2 images; a NeRF needs at least 3" in scene["error"]
    assert [s["state"] for s in scene["stages"]] == ["succeeded", "pending", "pending"]
    assert client.get(scene["links"]["points.ply"]).status_code == 200  # the reconstruction stays
    retry = client.post(f"/v1/scenes/{scene['id']}/retry")
    assert retry.status_code == 409 and "more photos" in retry.json()["detail"]


def test_registration_problem_names_the_counts_and_the_unregistered_images():
    report = {
        "images_registered": 2,
        "images_total": 3,
        "unregistered": [{"image": "3.png", "reason": "few"}],
    }
    assert registration_problem(report, 2) is None
    assert registration_problem(report, 3) == (
        "the reconstruction registered 2 of 3 images; a NeRF needs at least 3 (not registered: 3.png: few)"
    )


@pytest.mark.parametrize(
    ("data", "files", "expected"),
    [
        ({}, [], "images: upload the photos"),
        ({"options": "{not json"}, None, "options: not valid JSON"),
        ({"options": json.dumps({"steps": 5, "minutes": 1})}, None, "give steps or minutes"),
        ({}, [("images", ("1.png", b"not a png", "image/png"))], "1.png is not a complete PNG/JPEG"),
        ({"train_max_side": "4"}, None, "train_max_side"),
        ({"views_share": "-1"}, None, "views_share"),
    ],
    ids=[
        "no-photos", "bad-json", "conflicting-options", "bad-image", "tiny-train-side", "negative-views-share"
    ],  # fmt: skip
)
def test_bad_input_is_refused_before_any_job_starts(client, shared_data, data, files, expected):
    files = unity_hall_files(shared_data / "unity_hall") if files is None else files
    response = client.post("/v1/scenes", files=files or None, data=data)
    assert response.status_code == 422 and expected in response.text, response.text
    assert client.get("/v1/jobs").json()["total"] == 0 and client.get("/v1/scenes").json()["total"] == 0


def test_a_zip_that_climbs_out_is_refused(client):
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        zf.writestr("../1.png", b"x")
    response = client.post(
        "/v1/scenes", files={"photos_zip": ("photos.zip", archive.getvalue(), "application/zip")}
    )
    assert response.status_code == 422 and "climbs out" in response.json()["detail"]


def unity_hall_zip(folder: Path) -> bytes:
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted(folder.iterdir()):
            if path.suffix in (".png", ".txt"):
                zf.write(path, f"unity_hall/{path.name}")
    return archive.getvalue()


@pytest.mark.slow
def test_cancel_retry_from_the_stage_and_delete_act_on_the_whole_scene(client, settings, shared_data):
    response = client.post(
        "/v1/scenes",
        files={"photos_zip": ("hall.zip", unity_hall_zip(shared_data / "unity_hall"), "application/zip")},
        data={"minutes": "30", "batch_rays": "64", "train_max_side": "64", "views_share": "0.1"},
    )
    assert response.status_code == 202, response.text
    scene_id = response.json()["id"]
    # 5 photos at 2.5 s each, 30 minutes of training, views within 10 % of it
    assert response.json()["expected_seconds"] == {
        "reconstruction": 12.5, "training": 1800.0, "views": 180.0, "total": 1992.5
    }  # fmt: skip
    training = wait_for_scene(client, scene_id, until=lambda s: s["stages"][1]["state"] == "running")
    reconstruction_id, nerf_id = training["stages"][0]["job_ids"][0], training["stages"][1]["job_ids"][0]
    assert client.app.state.store.get(nerf_id).params["train_config"]["max_side"] == 64

    cancelled = client.post(f"/v1/scenes/{scene_id}/cancel").json()
    assert cancelled["state"] == "cancelled" and cancelled["stage"] == "nerf"
    nerf_job = wait_for_job_state(client, nerf_id)
    assert nerf_job["state"] == "cancelled"
    assert client.post(f"/v1/scenes/{scene_id}/cancel").status_code == 409

    retried = client.post(f"/v1/scenes/{scene_id}/retry")
    assert retried.status_code == 202, retried.text
    body = retried.json()
    assert body["state"] == "running" and body["stage"] == "nerf"
    assert body["stages"][0]["job_ids"] == [reconstruction_id]  # the reconstruction is not run again
    new_nerf = body["stages"][1]["job_ids"][0]
    assert new_nerf != nerf_id and client.get(f"/v1/jobs/{new_nerf}").json()["retry_of"] == nerf_id

    assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 404
    for job_id in (reconstruction_id, nerf_id, new_nerf):
        assert client.get(f"/v1/jobs/{job_id}").status_code == 404
        assert not (settings.jobs_dir / job_id).exists()


def wait_for_job_state(client: TestClient, job_id: str) -> dict:
    deadline = time.monotonic() + 30
    while (job := client.get(f"/v1/jobs/{job_id}").json())["state"] == "running":
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    return job


@pytest.mark.slow
def test_the_scene_command_writes_every_stage_with_a_bar_each(tmp_path, shared_data):
    out = tmp_path / "scene"
    options = json.dumps({"batch_rays": 256, "checkpoint_every": 5, "val_every": 5})
    result = CliRunner().invoke(
        cli,
        ["scene", str(shared_data / "unity_hall"), "--out", str(out), "--steps", "5", "--options", options,
         "--orbit-frames", "2", "--render-max-side", "40", "--train-max-side", "100"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    camera = json.loads((out / "nerf" / "config.json").read_text())["camera"]
    assert max(camera["width"], camera["height"]) == 100
    assert Image.open(out / "held_out" / "1.png").size == (40, 30)
    for stage in ("reconstruction", "nerf", "views"):
        assert f"{stage} " in result.output
    assert (out / "reconstruction" / "points.ply").is_file() and (out / "nerf" / "config.json").is_file()
    assert Image.open(out / "orbit" / "orbit.gif").n_frames == 2
    metrics = json.loads((out / "held_out" / "metrics.json").read_text())
    assert len(metrics["per_image"]) == 1 and (out / "held_out" / "1.png").is_file()  # frames 0, 8, ...
    assert "held-out views 1" in result.output


def test_the_scene_commands_max_side_is_the_render_max_side_with_a_warning(
    tmp_path, shared_data, monkeypatch
):
    import service.pipeline

    seen = []

    def stop(photos_dir, out_dir, reconstruction_config, options, stage):
        seen.append(options)
        raise service.pipeline.StageFailed("reconstruction", "stopped after reading the options")

    monkeypatch.setattr(service.pipeline, "run_scene", stop)
    result = CliRunner().invoke(
        cli, ["scene", str(shared_data / "unity_hall"), "--out", str(tmp_path / "o"), "--max-side", "40"]
    )
    assert result.exit_code != 0 and "stopped after reading the options" in result.output
    assert "warning: --max-side is deprecated; it is --render-max-side" in result.output
    sides = [(o.orbit_max_side, o.held_out_max_side, o.train_config["max_side"]) for o in seen]
    assert sides == [(40, 40, None)]


@pytest.mark.slow
def test_the_scene_command_prints_the_expected_time_and_stops_at_too_few_registered_images(
    tmp_path, shared_data
):
    result = CliRunner().invoke(
        cli,
        ["scene", str(shared_data / "unity_hall"), "--out", str(tmp_path / "o"), "--minutes", "1",
         "--views-share", "0.5", "--min-registered-images", "6"],
    )  # fmt: skip
    assert result.exit_code != 0
    assert "expected: reconstruction 12 s, training 60 s, views 30 s, total 102 s (CPU)" in result.output
    assert "registered 5 of 5 images; a NeRF needs at least 6" in result.output
    assert (tmp_path / "o" / "reconstruction" / "report.json").is_file()


# ---- each scene is its own unit of failure ------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "overrides", "status", "expected"),
    [
        ({"orbit_frames": "720", "orbit_max_side": "4096"}, {}, 413, "SFMNERF_MAX_VIDEO_PIXELS"),
        ({"orbit_max_side": "200"}, {"max_render_pixels": 20_000}, 422, "SFMNERF_MAX_RENDER_PIXELS"),
        ({"orbit_max_side": "40", "held_out_max_side": "400"}, {"max_render_pixels": 20_000}, 422,
         "SFMNERF_MAX_RENDER_PIXELS"),
        ({"steps": "0"}, {}, 422, "steps"),
    ],
    ids=["video-budget", "orbit-frame-size", "held-out-size", "steps"],
)  # fmt: skip
def test_every_option_of_a_scene_is_checked_at_submit_time(
    tmp_path, shared_data, data, overrides, status, expected
):
    """The orbit's frames x pixels and both render sizes follow from the photos' size (800x600 here): a
    scene that could not render its views is refused before its reconstruction starts."""
    with TestClient(create_app(make_settings(tmp_path / "data", **overrides))) as client:
        response = client.post("/v1/scenes", files=unity_hall_files(shared_data / "unity_hall"), data=data)
        assert response.status_code == status and expected in response.text, response.text
        assert client.get("/v1/jobs").json()["total"] == 0 and client.get("/v1/scenes").json()["total"] == 0
        assert list((tmp_path / "data" / "jobs").iterdir()) == []


def test_a_scene_asking_for_a_gpu_this_machine_lacks_is_refused_like_a_nerf_job(client, shared_data):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    photos = unity_hall_files(shared_data / "unity_hall")
    scene = client.post("/v1/scenes", files=photos, data={"device": "cuda"})
    nerf = client.post("/v1/nerf", data={"reconstruction_id": "0" * 32, "device": "cuda"})
    assert scene.status_code == nerf.status_code == 422
    assert scene.json()["detail"] == nerf.json()["detail"] and "no CUDA GPU" in scene.json()["detail"]
    assert client.get("/v1/jobs").json()["total"] == 0


class RecordingExecutor:
    """Queues nothing: records the jobs the scene supervisor submits."""

    def __init__(self) -> None:
        self.submitted: list[str] = []

    def submit(self, job_id: str) -> None:
        self.submitted.append(job_id)

    def cancel(self, job_id: str) -> None:
        pass


def test_an_error_in_one_scenes_step_fails_that_scene_and_the_others_move_on(settings):
    """A broken report.json makes the step of one scene raise; that scene fails with the reason, keeps its
    reconstruction, and the other scene (older, so advanced after it) still moves on."""
    from service.kinds import JobKind, JobState
    from service.layout import RECONSTRUCTION_REPORT, output_dir
    from service.scene_supervisor import SceneSteps, SceneSupervisor
    from service.store import JobStore, Scene, new_job_id

    store = JobStore(settings.resolved_database_url)
    report = {"images_registered": 5, "images_total": 5, "unregistered": []}
    scenes = {}
    for name, text in (("healthy", json.dumps(report)), ("broken", "{not json")):
        job = store.create(JobKind.reconstruction, {})
        attempt = store.claim(job.id, worker="test")
        store.finish(job.id, attempt, JobState.succeeded)
        output_dir(settings, job.id).mkdir(parents=True)
        (output_dir(settings, job.id) / RECONSTRUCTION_REPORT).write_text(text)
        scene = Scene(id=new_job_id(), state=JobState.running, stage="reconstruction", log=[],
                      params={"train_config": {"model": "fast"}}, reconstruction_job_id=job.id)  # fmt: skip
        scenes[name] = store.create_scene(scene).id
        time.sleep(0.01)  # the broken scene is the newest: the supervisor comes to it first
    supervisor = SceneSupervisor(SceneSteps(store, RecordingExecutor(), settings))
    supervisor.advance_all()
    broken, healthy = store.get_scene(scenes["broken"]), store.get_scene(scenes["healthy"])
    assert broken.state == JobState.failed and broken.stage == "reconstruction"
    assert broken.error.startswith("reconstruction: unexpected error: JSONDecodeError"), broken.error
    assert store.get(broken.reconstruction_job_id).state == JobState.succeeded
    assert healthy.state == JobState.running and healthy.stage == "nerf", healthy.log
    store.dispose()


def _scene_at_the_nerf_stage(store, settings):
    """A running scene whose reconstruction succeeded and whose NeRF has not been started."""
    from service.kinds import JobKind, JobState
    from service.store import Scene, new_job_id

    job = store.create(JobKind.reconstruction, {})
    store.finish(job.id, store.claim(job.id, worker="test"), JobState.succeeded)
    scene = Scene(id=new_job_id(), state=JobState.running, stage="nerf", log=[],
                  params={"train_config": {"model": "fast"}}, reconstruction_job_id=job.id)  # fmt: skip
    return store.create_scene(scene)


def test_a_child_job_and_its_place_on_the_scene_are_written_together(settings):
    """The job and the scene's record of it are one transaction: a scene that does not exist gets no job."""
    from service.kinds import JobKind
    from service.store import JobStore
    from service.store.tables import SceneChild

    store = JobStore(settings.resolved_database_url)
    scene = _scene_at_the_nerf_stage(store, settings)
    job = store.create(JobKind.nerf, {}, scene_child=SceneChild(scene.id, "nerf_job_id"))
    assert store.get_scene(scene.id).nerf_job_id == job.id
    jobs_before = store.list()[1]
    with pytest.raises(LookupError, match="does not exist"):
        store.create(JobKind.nerf, {}, scene_child=SceneChild("0" * 32, "nerf_job_id"))
    with pytest.raises(ValueError, match="not a scene's child-job column"):
        store.create(JobKind.nerf, {}, scene_child=SceneChild(scene.id, "state"))
    assert store.list()[1] == jobs_before
    store.dispose()


def test_a_crash_right_after_a_child_job_starts_does_not_start_it_twice(settings, monkeypatch):
    """The supervisor dies between creating the scene's NeRF job and logging it; the next pass finds the
    job on the scene and starts no second one."""
    import service.scene_supervisor as supervision
    from service.kinds import JobKind
    from service.store import JobStore

    store = JobStore(settings.resolved_database_url)
    scene = _scene_at_the_nerf_stage(store, settings)

    def create_nerf(store, executor, settings, client, inputs, scene_child=None):
        job = store.create(JobKind.nerf, {}, scene_child=scene_child)
        executor.submit(job.id)
        return job

    def crash(*args, **kwargs):
        raise SystemExit("killed")

    monkeypatch.setattr(supervision, "create_nerf", create_nerf)
    executor = RecordingExecutor()
    steps = supervision.SceneSteps(store, executor, settings)
    with monkeypatch.context() as killed:
        killed.setattr(store, "update_scene", crash)
        with pytest.raises(SystemExit):
            steps.advance(store.get_scene(scene.id))
    steps.advance(store.get_scene(scene.id))
    nerf_jobs = [job for job in store.list()[0] if job.kind == JobKind.nerf]
    assert len(nerf_jobs) == 1 and executor.submitted == [nerf_jobs[0].id]
    assert store.get_scene(scene.id).nerf_job_id == nerf_jobs[0].id
    store.dispose()


def test_a_stage_refused_as_busy_waits_its_retry_after_and_starts_then(settings, monkeypatch):
    """Every upload check taken (a 429 with Retry-After 5 s) is no failure of the scene: it stays running at
    its stage, says so once in its log, is not tried again before the 5 s, and its NeRF starts after them.
    Any other refusal still fails the scene with the reason."""
    import service.scene_supervisor as supervision
    from service.errors import ServiceError, busy
    from service.kinds import JobKind, JobState
    from service.store import JobStore

    store = JobStore(settings.resolved_database_url)
    scene = _scene_at_the_nerf_stage(store, settings)
    clock = [1000.0]
    monkeypatch.setattr(supervision.time, "monotonic", lambda: clock[0])
    attempts = []

    def create_nerf(store, executor, settings, client, inputs, scene_child=None):
        attempts.append(clock[0])
        if len(attempts) <= 2:
            raise busy("reconstruction_id: all 2 upload checks are busy; retry after 5 s", 5)
        return store.create(JobKind.nerf, {}, scene_child=scene_child)

    monkeypatch.setattr(supervision, "create_nerf", create_nerf)
    steps = supervision.SceneSteps(store, RecordingExecutor(), settings)
    for now in (1000.0, 1001.0, 1004.9, 1005.0, 1009.9, 1010.0):
        clock[0] = now
        steps.advance(store.get_scene(scene.id))
    waiting = store.get_scene(scene.id)
    assert attempts == [1000.0, 1005.0, 1010.0]
    assert waiting.state == JobState.running and waiting.nerf_job_id is not None
    waits = [line for line in waiting.log if "NeRF waits: reconstruction_id: all 2 upload checks" in line]
    assert len(waits) == 1

    def refuse(*args, **kwargs):
        raise ServiceError(422, "bad options")

    refused = _scene_at_the_nerf_stage(store, settings)
    monkeypatch.setattr(supervision, "create_nerf", refuse)
    steps.advance(store.get_scene(refused.id))
    failed = store.get_scene(refused.id)
    assert failed.state == JobState.failed and failed.error == "nerf: the NeRF could not start: bad options"
    store.dispose()
