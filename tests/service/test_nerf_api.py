"""A real NeRF job on a tiny dataset: render while it trains, survive a service restart (resuming from its
checkpoint), then checkpoints, renders of a given pose and an orbit video through the API."""

from __future__ import annotations

import io
import json
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from PIL import Image

from service.app import create_app
from tests.service.conftest import TINY_MODEL_OPTIONS, make_settings, tiny_nerf_npz, wait_for_job

TINY_SIDE = 20
TRAIN_OPTIONS = {
    "checkpoint_every": 10,
    "val_every": 10,
    "log_every": 5,
    "seed": 0,
    "model_options": TINY_MODEL_OPTIONS,
}


@pytest.fixture(scope="module")
def tiny_npz(shared_data) -> bytes:
    return tiny_nerf_npz(shared_data / "lego_tiny.npz", TINY_SIDE)


def has_checkpoint(client: TestClient, job_id: str):
    def check(job: dict) -> bool:
        assert job["state"] in ("queued", "running"), job
        return bool(client.get(f"/v1/nerf/{job_id}/checkpoints").json())

    return check


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_npz):
    """A NeRF job started, rendered while running, interrupted by a restart, resumed and finished."""
    settings = make_settings(tmp_path_factory.mktemp("nerf") / "data", job_threads=1)
    record: dict = {}
    with TestClient(create_app(settings)) as client:
        response = client.post(
            "/v1/nerf",
            files={"dataset": ("tiny.npz", tiny_npz, "application/octet-stream")},
            data={
                "model": "vanilla",
                "steps": "400",
                "batch_rays": "64",
                "device": "cpu",
                "options": json.dumps(TRAIN_OPTIONS),
            },
        )
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        record["no_checkpoint_render"] = client.post(
            f"/v1/nerf/{job_id}/render", json={"c2w": np.eye(4).tolist(), "width": 8, "height": 8}
        )
        wait_for_job(client, job_id, until=has_checkpoint(client, job_id))
        record["running_render"] = client.post(
            f"/v1/nerf/{job_id}/render", json={"c2w": np.eye(4).tolist(), "width": 12, "height": 10}
        )
        record["running_state"] = client.get(f"/v1/jobs/{job_id}").json()["state"]
        record["step_before_restart"] = max(
            c["step"] for c in client.get(f"/v1/nerf/{job_id}/checkpoints").json()
        )
    # The service stopped with the job in flight; a new one picks it up.
    client = TestClient(create_app(settings))
    with client:
        job = wait_for_job(client, job_id)
        yield client, job, record, settings


def test_render_before_the_first_checkpoint_answers_409(trained):
    _, _, record, _ = trained
    response = record["no_checkpoint_render"]
    assert response.status_code == 409 and "no checkpoint yet" in response.json()["detail"]


def test_a_running_job_renders_from_its_latest_checkpoint(trained):
    _, _, record, _ = trained
    assert record["running_state"] == "running"
    response = record["running_render"]
    assert response.status_code == 200 and response.headers["content-type"] == "image/png", response.text


def test_a_restart_resumes_the_job_from_its_last_checkpoint(trained):
    client, job, record, settings = trained
    assert job["state"] == "succeeded" and job["attempt"] == 2, job
    lines = client.get(f"/v1/jobs/{job['id']}/logs").json()["lines"]
    assert any("resumes from its last checkpoint" in line for line in lines)
    resumed = [line for line in lines if line.startswith("resuming from the checkpoint at step")]
    assert resumed and int(resumed[0].split()[-1]) >= record["step_before_restart"]
    steps = [
        m["step"] for m in client.get(f"/v1/nerf/{job['id']}").json()["metrics"] if m.get("loss") is not None
    ]
    assert steps[-1] == 400 and steps[0] == 5
    assert job["result"]["step"] == 400


def test_metrics_and_checkpoints_are_listed(trained):
    client, job, _, _ = trained
    body = client.get(f"/v1/nerf/{job['id']}").json()
    assert body["config"] and body["latest_step"] == 400
    training = [m for m in body["metrics"] if m.get("loss") is not None]
    assert all(m["psnr"] is not None for m in training)
    checkpoints = client.get(f"/v1/nerf/{job['id']}/checkpoints").json()
    assert [c["step"] for c in checkpoints if c["is_latest"]] == [400]
    assert all(c["size_bytes"] > 0 for c in checkpoints)


def test_a_checkpoint_downloads_as_a_loadable_file(trained, tmp_path):
    client, job, _, _ = trained
    response = client.get(f"/v1/nerf/{job['id']}/checkpoints/400")
    assert response.status_code == 200
    path = tmp_path / "ckpt.pt"
    path.write_bytes(response.content)
    payload = torch.load(path, map_location="cpu", weights_only=False)
    assert payload["step"] == 400 and payload["model_name"] == "vanilla"
    assert client.get(f"/v1/nerf/{job['id']}/checkpoints/7").status_code == 404


@pytest.mark.parametrize(
    "camera",
    [
        {"c2w": [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0.5], [0, 0, 0, 1]]},
        {"eye": [0.0, -4.0, 1.0], "look_at": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_x_deg": 40.0},
        {"eye": [4.0, 0.0, 0.0], "look_at": [0.0, 0.0, 0.0], "fx": 30.0, "checkpoint": "best"},
    ],
    ids=["c2w", "look-at-fov", "look-at-fx-best"],
)
def test_a_render_of_a_given_pose_is_a_png_of_the_requested_size(trained, camera):
    client, job, _, _ = trained
    response = client.post(f"/v1/nerf/{job['id']}/render", json={**camera, "width": 24, "height": 16})
    assert response.status_code == 200, response.text
    image = Image.open(io.BytesIO(response.content))
    assert image.format == "PNG" and image.size == (24, 16)
    assert np.asarray(image).std() > 0  # an image, not a blank


def test_a_render_without_a_camera_is_the_default_view_a_registered_camera(trained):
    client, job, _, _ = trained
    path = client.get(f"/v1/nerf/{job['id']}/camera-path", params={"num_frames": 5})
    assert path.status_code == 200, path.text
    cameras, default_view = np.asarray(path.json()["cameras"]), np.asarray(path.json()["default_view"])
    assert np.abs(cameras - default_view).max(axis=(1, 2)).min() < 1e-6 and len(path.json()["path"]) == 5
    default = client.post(f"/v1/nerf/{job['id']}/render", json={"width": 24, "height": 16})
    given = client.post(
        f"/v1/nerf/{job['id']}/render",
        json={"c2w": path.json()["default_view"], "frame": "data", "width": 24, "height": 16},
    )
    assert default.status_code == 200 and given.status_code == 200, default.text
    assert np.array_equal(
        np.asarray(Image.open(io.BytesIO(default.content))), np.asarray(Image.open(io.BytesIO(given.content)))
    )


def test_a_view_that_sees_nothing_is_a_422_saying_so_unless_allowed(trained, tiny_npz):
    client, _, _, _ = trained
    empty_field = {"initial_voxels": 16**3, "final_voxels": 16**3, "initial_alpha": 1e-9}  # fast, bounded
    response = client.post(
        "/v1/nerf",
        files={"dataset": ("tiny.npz", tiny_npz, "application/octet-stream")},
        data={"model": "fast", "steps": "1", "batch_rays": "16", "device": "cpu",
              "options": json.dumps({"lr": 1e-12, "model_options": empty_field})},
    )  # fmt: skip
    job = wait_for_job(client, response.json()["id"])
    assert job["state"] == "succeeded", job
    refused = client.post(f"/v1/nerf/{job['id']}/render", json={"width": 24, "height": 16})
    assert refused.status_code == 422 and "sees nothing of the scene" in refused.json()["detail"]
    allowed = client.post(
        f"/v1/nerf/{job['id']}/render", json={"width": 24, "height": 16, "allow_empty_view": True}
    )
    assert allowed.status_code == 200 and Image.open(io.BytesIO(allowed.content)).size == (24, 16)


def test_a_camera_path_of_a_run_without_registered_cameras_is_a_422(trained):
    client, job, _, settings = trained
    config_path = settings.jobs_dir / job["id"] / "output" / "config.json"
    stored = config_path.read_text()
    try:
        config_path.write_text(json.dumps({**json.loads(stored), "cameras": {"c2w": [], "photos": False}}))
        response = client.get(f"/v1/nerf/{job['id']}/camera-path")
        assert response.status_code == 422 and "no registered cameras" in response.json()["detail"]
    finally:
        config_path.write_text(stored)


def test_render_limits_and_unknown_checkpoints_are_4xx(trained):
    client, job, _, settings = trained
    side = int(settings.max_render_pixels**0.5) + 1
    big = client.post(
        f"/v1/nerf/{job['id']}/render", json={"c2w": np.eye(4).tolist(), "width": side, "height": side}
    )
    assert big.status_code == 422 and "SFMNERF_MAX_RENDER_PIXELS" in big.json()["detail"]
    missing = client.post(
        f"/v1/nerf/{job['id']}/render",
        json={"c2w": np.eye(4).tolist(), "width": 8, "height": 8, "checkpoint": 3},
    )
    assert missing.status_code == 422 and "checkpoint" in missing.json()["detail"]


def test_an_orbit_video_is_queued_and_fetched(trained):
    client, job, _, _ = trained
    assert client.get(f"/v1/nerf/{job['id']}/video").status_code == 404
    response = client.post(f"/v1/nerf/{job['id']}/video", json={"num_frames": 3, "width": 16, "height": 16})
    assert response.status_code == 202 and response.headers["Location"].startswith("/v1/jobs/")
    video_job = wait_for_job(client, response.json()["id"])
    assert video_job["state"] == "succeeded", client.get(f"/v1/jobs/{video_job['id']}/logs").json()
    video = client.get(f"/v1/nerf/{job['id']}/video")
    assert video.status_code == 200 and video.headers["content-type"] == "image/gif"
    gif = Image.open(io.BytesIO(video.content))
    assert gif.size == (16, 16) and gif.n_frames == 3


def blender_zip(root: Path, train_views: int = 3, val_views: int = 1) -> bytes:
    """A few views of the Lego Blender dataset, zipped under a top-level folder as people zip them."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for split, count in (("train", train_views), ("val", val_views)):
            meta = json.loads((root / f"transforms_{split}.json").read_text())
            meta["frames"] = meta["frames"][:count]
            zf.writestr(f"lego/transforms_{split}.json", json.dumps(meta))
            for frame in meta["frames"]:
                name = f"{frame['file_path'].removeprefix('./')}.png"
                zf.write(root / name, f"lego/{name}")
    return buffer.getvalue()


def test_a_blender_zip_upload_becomes_a_nerf_job(client, settings, shared_data):
    archive = blender_zip(shared_data / "lego_200")
    response = client.post(
        "/v1/nerf",
        files={"dataset": ("lego.zip", archive, "application/zip")},
        data={"model": "fast", "steps": "5"},
    )
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    assert (settings.jobs_dir / job_id / "input" / "dataset" / "lego" / "transforms_train.json").is_file()
    assert not (settings.jobs_dir / job_id / "input" / "upload.zip").exists()
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 200
    assert wait_for_job(client, job_id, timeout=10)["state"] == "cancelled"


def test_an_identical_render_is_answered_from_the_render_cache(trained):
    client, job, _, settings = trained
    request = {
        "eye": [3.0, 1.0, 1.0],
        "look_at": [0.0, 0.0, 0.0],
        "width": 20,
        "height": 14,
        "checkpoint": 400,
    }
    first = client.post(f"/v1/nerf/{job['id']}/render", json=request)
    assert first.status_code == 200, first.text
    cached = list((settings.jobs_dir / job["id"] / "renders").glob("*.png"))
    assert [p.read_bytes() for p in cached].count(first.content) == 1
    # Replace the cached image: an identical request answered from the cache returns the replacement.
    marker = io.BytesIO()
    Image.new("RGB", (20, 14), (255, 0, 0)).save(marker, format="PNG")
    next(p for p in cached if p.read_bytes() == first.content).write_bytes(marker.getvalue())
    again = client.post(f"/v1/nerf/{job['id']}/render", json={**request, "checkpoint": "latest"})
    assert again.content == marker.getvalue()
    other_size = client.post(f"/v1/nerf/{job['id']}/render", json={**request, "width": 22})
    assert Image.open(io.BytesIO(other_size.content)).size == (22, 14)


def test_renders_beyond_the_queue_get_503_with_retry_after_while_status_reads_stay_fast(trained):
    _, job, _, settings = trained
    one_slot = settings.model_copy(update={"render_queue_size": 1, "render_cache_per_job": 0})
    with TestClient(create_app(one_slot)) as client:  # a second API process on the same data folder
        camera = {"c2w": np.eye(4).tolist(), "width": 16, "height": 16}
        answers: list = []
        first = threading.Thread(
            target=lambda: answers.append(client.post(f"/v1/nerf/{job['id']}/render", json=camera))
        )
        first.start()  # its render processes start now (seconds): the only slot stays taken meanwhile
        deadline = time.monotonic() + 10
        while client.app.state.renders._in_flight == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        busy = client.post(f"/v1/nerf/{job['id']}/render", json=camera)
        started = time.monotonic()
        status = client.get(f"/v1/jobs/{job['id']}")
        status_seconds = time.monotonic() - started
        first.join(timeout=120)
    assert busy.status_code == 503 and busy.headers["Retry-After"].isdigit(), busy.text
    assert "SFMNERF_RENDER_QUEUE_SIZE" in busy.json()["detail"]
    assert status.status_code == 200 and status_seconds < 2.0
    assert answers[0].status_code == 200


def test_a_video_over_the_frame_budget_is_refused_naming_the_setting(trained):
    client, job, _, settings = trained
    side = int(settings.max_render_pixels**0.5)  # each frame is within the per-frame limit
    response = client.post(
        f"/v1/nerf/{job['id']}/video", json={"num_frames": 720, "width": side, "height": side}
    )
    assert response.status_code == 413 and "SFMNERF_MAX_VIDEO_PIXELS" in response.json()["detail"]
