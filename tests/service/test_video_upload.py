"""A video uploaded in place of photos: /v1/reconstructions and /v1/scenes take one video file in `images`;
a corrupt, unsupported or too large video is refused naming the file and the limit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from neural import load_dataset
from service.app import create_app
from service.runner import output_dir
from tests.estimation.io.clips import encode_clip, held_views, lego_centres, walk_order
from tests.service.conftest import make_settings, wait_for_job


@pytest.fixture(scope="module")
def walk_clip(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """40 lego views along a walk, one frame each at 10 fps: 4 s of H.264."""
    frames, _ = held_views(walk_order(lego_centres(), 40), hold=1)
    return encode_clip(frames, tmp_path_factory.mktemp("clip") / "walk.mp4", fps=10).read_bytes()


def video_file(name: str, content: bytes, media_type: str = "video/mp4") -> list:
    return [("images", (name, content, media_type))]


def test_a_reconstruction_job_from_a_video_reconstructs_its_keyframes(client, settings, walk_clip):
    response = client.post("/v1/reconstructions", files=video_file("walk.mp4", walk_clip))
    assert response.status_code == 202, response.text
    job = wait_for_job(client, response.json()["id"])
    assert job["state"] == "succeeded", client.get(f"/v1/jobs/{job['id']}/logs").json()
    reconstruction = client.get(f"/v1/reconstructions/{job['id']}").json()
    video = reconstruction["statistics"]["video"]
    assert video["file"] == "walk.mp4" and video["frames_decoded"] == 40
    assert reconstruction["statistics"]["images_total"] == video["keyframes"]
    assert len(reconstruction["cameras"]) == reconstruction["statistics"]["images_registered"] >= 3
    transforms = client.get(f"/v1/reconstructions/{job['id']}/transforms.json").json()
    assert all(frame["file_path"].startswith("frames/") for frame in transforms["frames"])
    # What a scene's NeRF stage reads: the keyframes as the dataset's images.
    dataset = load_dataset(output_dir(settings, job["id"]))
    assert len(dataset.image_names) == len(reconstruction["cameras"])
    assert all(name.startswith("frames/") for name in dataset.image_names)


@pytest.mark.parametrize(("name", "content", "problem"), [
    ("broken.mp4", b"\x00\x00\x00\x18ftypmp42" + bytes(4000), "not a readable video"),
    ("noise.mov", np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8).tobytes(),
     "not a readable video"),
], ids=["truncated-mp4", "noise-mov"])
def test_a_corrupt_video_is_a_422_naming_it(client, settings, name, content, problem):
    for route in ("/v1/reconstructions", "/v1/scenes"):
        response = client.post(route, files=video_file(name, content))
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert detail.startswith(f"images: {name}: {problem}"), detail
        assert str(settings.data_dir) not in detail and "/jobs/" not in detail


def test_a_format_that_is_no_supported_video_is_a_422_naming_it(client, tmp_path):
    from PIL import Image

    Image.new("RGB", (16, 16)).save(tmp_path / "photo.png")
    response = client.post("/v1/reconstructions",
                           files=video_file("photo.mp4", (tmp_path / "photo.png").read_bytes()))
    assert response.status_code == 422
    assert "images: photo.mp4: a 'png_pipe' file is not a supported video" in response.json()["detail"]


def test_a_video_comes_alone(client, walk_clip):
    response = client.post("/v1/reconstructions", files=[*video_file("walk.mp4", walk_clip),
                                                         ("images", ("a.png", b"x", "image/png"))])
    assert response.status_code == 422 and "one video" in response.json()["detail"]
    response = client.post("/v1/reconstructions", files=[*video_file("walk.mp4", walk_clip),
                                                         ("matches", ("matching1.txt", b"", "text/plain"))])
    assert response.status_code == 422 and response.json()["detail"].startswith("matches: ")
    response = client.post("/v1/reconstructions", files=video_file("walk.bin", walk_clip))
    assert response.status_code == 422 and "walk.bin" in response.json()["detail"]


@pytest.mark.parametrize(("limit", "value", "named"), [
    ("max_input_video_bytes", 1000, "SFMNERF_MAX_INPUT_VIDEO_BYTES=1000"),
    ("max_input_video_seconds", 2.0, "walk.mp4 lasts 4.0 s, more than the limit "
                                     "SFMNERF_MAX_INPUT_VIDEO_SECONDS=2"),
    ("max_input_video_pixels", 100 * 100, "walk.mp4 has frames of 200x200 pixels"),
])
def test_limits_of_size_duration_and_resolution_are_413s_naming_them(tmp_path, walk_clip, limit, value,
                                                                     named):
    settings = make_settings(tmp_path / "data", **{limit: value})
    with TestClient(create_app(settings)) as client:
        response = client.post("/v1/reconstructions", files=video_file("walk.mp4", walk_clip))
        assert response.status_code == 413, response.text
        assert named in response.json()["detail"]
        assert limit in client.get("/v1/info").json()["limits"]
        assert not any(Path(settings.jobs_dir).glob("*/input/walk.mp4"))    # the refused job is gone
