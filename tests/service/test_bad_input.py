"""Every kind of bad input gets its 4xx with a message naming the field, file or limit; never a 5xx."""

from __future__ import annotations

import io
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from service.app import create_app
from tests.service.conftest import make_settings, unity_hall_files

UNKNOWN_ID = "0" * 32


def png_bytes(width: int = 8, height: int = 6, color: tuple[int, int, int] = (10, 20, 30)) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), color).save(buffer, format="PNG")
    return buffer.getvalue()


def replace_file(files: list, name: str, content: bytes, field: str | None = None) -> list:
    """The upload with the file called `name` replaced (or added under `field`)."""
    kept = [f for f in files if f[1][0] != name]
    return [
        *kept,
        (field or next(f[0] for f in files if f[1][0] == name), (name, content, "application/octet-stream")),
    ]


@pytest.fixture(scope="module")
def unity(shared_data: Path) -> list:
    return unity_hall_files(shared_data / "unity_hall")


def assert_rejected(response, status: int, *words: str) -> None:
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    text = detail if isinstance(detail, str) else str(detail)
    for word in words:
        assert word in text, f"{word!r} not in {text!r}"


def test_a_non_image_file_is_rejected_naming_the_file(client, unity):
    files = replace_file(unity, "3.png", b"this is not an image")
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "images", "3.png")


@pytest.mark.parametrize(
    "content", [b"x", b"\x89PNG\r\n\x1a\n", png_bytes()[:60]], ids=["1-byte", "magic", "cut"]
)
@pytest.mark.parametrize("route", ["/v1/reconstructions", "/v1/scenes"])
def test_a_broken_image_is_named_as_uploaded_and_no_server_path_is_shown(client, settings, route, content):
    """The decoder quotes the file it opened (the job's input folder): the message names the upload."""
    files = [("images", ("1.png", png_bytes(), "image/png")), ("images", ("my photo.png", content, "x/y"))]
    response = client.post(route, files=files, data={"K": "1 0 4 0 1 3 0 0 1"})
    assert_rejected(response, 422, "images", "my_photo.png")
    detail = response.json()["detail"]
    assert str(settings.data_dir) not in detail and "/jobs/" not in detail and "/input" not in detail


def test_a_truncated_image_is_rejected_naming_the_file(client, unity, shared_data):
    whole = (shared_data / "unity_hall" / "2.png").read_bytes()
    files = replace_file(unity, "2.png", whole[: len(whole) // 2])
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "images", "2.png")


def test_an_image_of_another_format_is_rejected(client, unity):
    gif = io.BytesIO()
    Image.new("RGB", (800, 600)).save(gif, format="GIF")
    assert_rejected(
        client.post("/v1/reconstructions", files=replace_file(unity, "4.png", gif.getvalue())),
        422,
        "4.png",
        "PNG and JPEG",
    )


def test_images_of_different_sizes_are_rejected(client, unity):
    files = replace_file(unity, "5.png", png_bytes(640, 480))
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "5.png", "same size")


def test_a_single_image_is_rejected(client):
    files = [
        ("images", ("1.png", png_bytes(), "image/png")),
        ("calibration", ("c.txt", b"1 0 4\n0 1 3\n0 0 1", "t")),
    ]
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "at least 2")


def test_missing_images_field_is_rejected(client):
    assert_rejected(client.post("/v1/reconstructions", data={"K": "1 0 0 0 1 0 0 0 1"}), 422, "images")


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"nFeatures: 1\n2 255 0 0 10.0 20.0 2\n", ["matching1.txt", "line 2"]),
        (b"2 255 0 0 10.0 abc 2 30.0 40.0\n", ["matching1.txt", "line 1", "abc"]),
        (b"2 255 0 0 10.0 20.0 9 30.0 40.0\n", ["matching1.txt", "line 1", "9"]),
    ],
    ids=["too-few-numbers", "non-numeric", "unknown-image-id"],
)
def test_a_malformed_match_file_is_rejected_naming_file_and_line(client, unity, content, words):
    files = replace_file(unity, "matching1.txt", content)
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "matches", *words)


def test_a_match_file_must_be_named_after_an_image(client, unity):
    files = [*unity, ("matches", ("features.txt", b"", "text/plain"))]
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "features.txt", "matching<i>.txt")
    files = [*unity, ("matches", ("matching7.txt", b"2 0 0 0 1 1 1 2 2\n", "text/plain"))]
    assert_rejected(
        client.post("/v1/reconstructions", files=files), 422, "matching7.txt", "no image with id 7"
    )


def test_photos_without_calibration_are_accepted(client, shared_data):
    """The reconstruction then calibrates the camera itself (EXIF focal length or a prior, refined)."""
    files = unity_hall_files(shared_data / "unity_hall", with_calibration=False)
    response = client.post("/v1/reconstructions", files=files)
    assert response.status_code == 202, response.text


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"1 0 400\n0 1 300\n", ["3 rows"]),
        (b"1 0 400\n0 x 300\n0 0 1\n", ["line 2", "'x'"]),
        (b"1 0 400\n0 1 300\n0 1 1\n", ["last row"]),
    ],
    ids=["two-rows", "non-numeric", "bad-last-row"],
)
def test_a_malformed_calibration_is_rejected(client, unity, content, words):
    files = replace_file(unity, "calibration.txt", content)
    assert_rejected(client.post("/v1/reconstructions", files=files), 422, "calibration", *words)


def test_k_as_numbers_needs_nine_of_them_and_not_a_file_too(client, unity, shared_data):
    no_file = unity_hall_files(shared_data / "unity_hall", with_calibration=False)
    assert_rejected(
        client.post("/v1/reconstructions", files=no_file, data={"K": "1 0 400 0 1 300 0 0"}),
        422,
        "K",
        "9 numbers",
        "found 8",
    )
    assert_rejected(
        client.post("/v1/reconstructions", files=unity, data={"K": "1 0 400 0 1 300 0 0 1"}), 422, "either"
    )


def test_matches_mode_needs_match_files(client, unity):
    files = [f for f in unity if f[0] != "matches"]
    assert_rejected(
        client.post("/v1/reconstructions", files=files, data={"features": "matches"}), 422, "matching<i>.txt"
    )


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("features", "magic"),
        ("ransac_threshold_px", "-1"),
        ("ba_max_iterations", "0"),
        ("webhook_url", "ftp://x"),
    ],
)
def test_bad_options_are_rejected_naming_the_field(client, unity, field, value):
    assert_rejected(client.post("/v1/reconstructions", files=unity, data={field: value}), 422, field)


def test_too_many_images_answer_413_naming_the_limit(tmp_path, unity):
    with TestClient(create_app(make_settings(tmp_path, max_images=3))) as client:
        assert_rejected(client.post("/v1/reconstructions", files=unity), 413, "SFMNERF_MAX_IMAGES=3")


def test_too_many_pixels_answer_413_naming_the_limit(tmp_path, unity):
    with TestClient(create_app(make_settings(tmp_path, max_image_pixels=1000))) as client:
        assert_rejected(client.post("/v1/reconstructions", files=unity), 413, "SFMNERF_MAX_IMAGE_PIXELS=1000")


def test_a_too_large_body_answers_413_naming_the_limit(tmp_path, unity):
    with TestClient(create_app(make_settings(tmp_path, max_upload_bytes=100_000))) as client:
        assert_rejected(
            client.post("/v1/reconstructions", files=unity), 413, "SFMNERF_MAX_UPLOAD_BYTES=100000"
        )
        # Streamed without a Content-Length: counted while it arrives.
        chunks = (b"x" * 50_000 for _ in range(4))
        response = client.post(
            "/v1/reconstructions",
            content=chunks,
            headers={"Content-Type": "multipart/form-data; boundary=abc"},
        )
        assert_rejected(response, 413, "SFMNERF_MAX_UPLOAD_BYTES")


def test_rejected_uploads_leave_no_job_and_no_files(client, settings, unity):
    client.post("/v1/reconstructions", files=replace_file(unity, "3.png", b"garbage"))
    assert client.get("/v1/jobs").json()["total"] == 0
    assert list(settings.jobs_dir.iterdir()) == []


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("get", "/v1/jobs/{id}"),
        ("get", "/v1/jobs/{id}/logs"),
        ("post", "/v1/jobs/{id}/cancel"),
        ("post", "/v1/jobs/{id}/retry"),
        ("delete", "/v1/jobs/{id}"),
        ("get", "/v1/reconstructions/{id}"),
        ("get", "/v1/reconstructions/{id}/points.ply"),
        ("get", "/v1/reconstructions/{id}/colmap.zip"),
        ("get", "/v1/reconstructions/{id}/transforms.json"),
        ("get", "/v1/reconstructions/{id}/figures/a.png"),
        ("get", "/v1/nerf/{id}"),
        ("get", "/v1/nerf/{id}/checkpoints"),
        ("get", "/v1/nerf/{id}/checkpoints/10"),
        ("get", "/v1/nerf/{id}/video"),
    ],
)
def test_an_unknown_job_id_answers_404_naming_it(client, method, path):
    response = getattr(client, method)(path.format(id=UNKNOWN_ID))
    assert_rejected(response, 404, UNKNOWN_ID)


@pytest.mark.parametrize("query", ["state=bogus", "kind=bogus", "limit=0", "limit=100000", "offset=-1"])
def test_bad_job_list_filters_answer_422(client, query):
    assert client.get(f"/v1/jobs?{query}").status_code == 422


def test_bad_log_offset_answers_422(client):
    assert client.get(f"/v1/jobs/{UNKNOWN_ID}/logs?offset=-3").status_code == 422


@pytest.mark.parametrize(
    "body",
    [
        {"eye": [0, 0, 1], "width": 10, "height": 10},
        {"eye": [0, 0, 1], "look_at": [0, 0, 1], "width": 10, "height": 10},
        {"eye": [0, 0, 1], "look_at": [0, 0, 0], "up": [0, 0, 1], "width": 10, "height": 10},
        {"c2w": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": 10, "height": 10},
        {"c2w": np.eye(4).tolist(), "eye": [0, 0, 1], "look_at": [0, 0, 0], "width": 10, "height": 10},
        {"c2w": np.eye(4).tolist(), "width": 0, "height": 10},
        {"c2w": np.eye(4).tolist(), "width": 10, "height": 10, "fx": 5, "fov_x_deg": 40},
        {"c2w": (np.eye(4) * 1e300).tolist(), "width": 10, "height": 10},
    ],
    ids=["eye-without-look-at", "eye-is-target", "up-along-view", "c2w-3x3", "two-cameras", "zero-width",
         "fx-and-fov", "c2w-beyond-the-scene"],
)
def test_a_bad_render_request_answers_422(client, body):
    assert client.post(f"/v1/nerf/{UNKNOWN_ID}/render", json=body).status_code == 422


def test_a_camera_far_beyond_the_scene_answers_422_naming_the_field(client):
    """Coordinates of ~1e156 made the look-at maths overflow (numpy's RuntimeWarning) before the
    degenerate camera was refused; now the field's bound refuses them first."""
    body = {"eye": [-3.7e148, -1.6e156, 9.2], "look_at": [6.9e16, 600, 8.3e15], "width": 10, "height": 10}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        response = client.post(f"/v1/nerf/{UNKNOWN_ID}/render", json=body)
    assert response.status_code == 422
    assert {tuple(error["loc"][1:3]) for error in response.json()["detail"]} >= {("eye", 0), ("eye", 1)}


def test_render_with_a_non_json_body_answers_422(client):
    response = client.post(
        f"/v1/nerf/{UNKNOWN_ID}/render", content=b"{not json", headers={"Content-Type": "application/json"}
    )
    assert response.status_code == 422


def _zip(entries: dict[str, bytes], symlinks: dict[str, str] | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        for name, target in (symlinks or {}).items():
            info = zipfile.ZipInfo(name)
            info.external_attr = 0o120777 << 16
            zf.writestr(info, target)
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("archive", "status", "words"),
    [
        (b"PK\x03\x04 definitely not a zip", 422, ["dataset", "not a valid zip"]),
        (_zip({"../evil.txt": b"x"}), 422, ["../evil.txt", ".."]),
        (_zip({"/etc/evil.txt": b"x"}), 422, ["/etc/evil.txt", "absolute"]),
        (
            _zip({"transforms_train.json": b"{}"}, symlinks={"link.png": "/etc/passwd"}),
            422,
            ["link.png", "link"],
        ),
        (_zip({"bomb.bin": bytes(50 * 2**20)}), 413, ["bomb.bin", "SFMNERF_MAX_ZIP_RATIO"]),
        (_zip({"readme.txt": b"hello"}), 422, ["transforms_train.json"]),
    ],
    ids=["not-a-zip", "traversal", "absolute", "symlink", "bomb", "not-blender"],
)
def test_unsafe_or_wrong_dataset_zips_are_refused(client, settings, archive, status, words):
    response = client.post(
        "/v1/nerf", files={"dataset": ("scene.zip", archive, "application/zip")}, data={"steps": "1"}
    )
    assert_rejected(response, status, *words)
    assert not (settings.data_dir.parent / "evil.txt").exists() and not Path("/etc/evil.txt").exists()
    assert list(settings.jobs_dir.iterdir()) == []


def test_a_nerf_job_needs_exactly_one_dataset(client):
    assert_rejected(client.post("/v1/nerf", data={"steps": "1"}), 422, "exactly one")
    response = client.post(
        "/v1/nerf",
        files={"dataset": ("d.npz", b"x", "application/zip")},
        data={"reconstruction_id": UNKNOWN_ID},
    )
    assert_rejected(response, 422, "exactly one")


def test_a_nerf_job_on_an_unknown_reconstruction_answers_404(client):
    assert_rejected(client.post("/v1/nerf", data={"reconstruction_id": UNKNOWN_ID}), 404, UNKNOWN_ID)


@pytest.mark.parametrize(
    ("data", "words"),
    [
        ({"options": "{not json"}, ["options", "JSON"]),
        ({"options": "[1]"}, ["options", "object"]),
        ({"options": '{"warp_speed": 9}'}, ["warp_speed"]),
        ({"steps": "5", "minutes": "1"}, ["steps or minutes"]),
        ({"model": "gaussian"}, ["model"]),
        ({"batch_rays": "0"}, ["batch_rays"]),
    ],
    ids=["bad-json", "not-object", "unknown-field", "steps-and-minutes", "unknown-model", "zero-rays"],
)
def test_bad_training_options_answer_422_naming_them(client, data, words):
    response = client.post("/v1/nerf", data={"reconstruction_id": UNKNOWN_ID, **data})
    assert_rejected(response, 422, *words)


def test_a_broken_npz_dataset_answers_422(client, settings):
    npz = io.BytesIO()
    np.savez(npz, images=np.zeros((2, 4, 4, 3), np.float32))  # no poses, no focal
    response = client.post("/v1/nerf", files={"dataset": ("tiny.npz", npz.getvalue(), "application/zip")})
    assert_rejected(response, 422, "dataset")
    assert list(settings.jobs_dir.iterdir()) == []


def test_the_api_token_protects_every_route_but_health_checks(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, api_token="s3cret"))) as client:
        assert client.get("/healthz").status_code == 200
        assert client.get("/readyz").status_code == 200
        for path in ("/v1/jobs", "/v1/info", f"/v1/jobs/{UNKNOWN_ID}"):
            assert client.get(path).status_code == 401
            assert client.get(path, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.post("/v1/reconstructions").status_code == 401
        assert client.get("/v1/jobs", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert (
            client.get("/v1/info", headers={"Authorization": "Bearer s3cret"}).json()["executor"] == "local"
        )
