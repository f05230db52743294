"""The service as an attacker probes it: paths out of a dataset, memory bombs, requests without a token,
other clients' jobs, webhooks to internal addresses, and answers that would leak server internals."""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import os
import socket
import struct
import time
import zipfile
import zlib
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from service.app import create_app
from service.kinds import JobKind, JobState
from service.layout import job_dir
from service.runner import execute
from service.store import JobStore, Scene, new_job_id
from tests.service.conftest import WebhookReceiver, make_settings, wait_for_job

UNKNOWN_ID = "0" * 32
CAMERA_ANGLE_X = 0.69


def png_bytes(width: int = 8, height: int = 8) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (200, 100, 50)).save(buffer, format="PNG")
    return buffer.getvalue()


def blender_zip(file_paths: list[str], images: dict[str, bytes] | None = None) -> bytes:
    """A Blender-format dataset zip whose train frames name `file_paths`, with `images` as its files."""
    frames = [{"file_path": path, "transform_matrix": np.eye(4).tolist()} for path in file_paths]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("transforms_train.json", json.dumps({"camera_angle_x": CAMERA_ANGLE_X, "frames": frames}))
        for name, data in (images if images is not None else {"train/r_0.png": png_bytes()}).items():
            zf.writestr(name, data)
    return buffer.getvalue()


def post_dataset(client: TestClient, name: str, content: bytes, **data: str):
    return client.post(
        "/v1/nerf", files={"dataset": (name, content, "application/zip")}, data={"steps": "1", **data}
    )


def assert_refused(response, status: int, *words: str) -> str:
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    for word in words:
        assert word in detail, f"{word!r} not in {detail!r}"
    return detail


# ---- 1. every path a dataset names stays inside it -------------------------------------------------------


def test_frames_pointing_at_another_jobs_files_are_refused_naming_the_frame(client, settings):
    """Another job's photo, by `..` and by absolute path, existing or not: one refusal, no server path."""
    other = job_dir(settings, "f" * 32) / "input"
    other.mkdir(parents=True)
    (other / "1.png").write_bytes(png_bytes())
    details = []
    for target in ("1.png", "missing.png"):
        for file_path in (f"../../../{'f' * 32}/input/{target}", str(other / target)):
            response = post_dataset(client, "scene.zip", blender_zip(["train/r_0", file_path]))
            detail = assert_refused(response, 422, "transforms_train.json frames[1]", "outside the dataset")
            assert str(settings.data_dir) not in detail
            details.append(detail.replace(target, "<target>"))
    assert details[0] == details[2] and details[1] == details[3]  # existing or not: the same answer
    assert sorted(p.name for p in settings.jobs_dir.iterdir()) == ["f" * 32]  # no folder left


# ---- 2. bounded upload checks -----------------------------------------------------------------------------


def npy_header_member(shape: tuple[int, ...], dtype: str) -> bytes:
    """An .npy file's header for `shape` and `dtype`, followed by only a few bytes of data."""
    header = {"descr": np.dtype(dtype).str if dtype != "O" else "|O", "fortran_order": False, "shape": shape}
    text = repr(header).encode("latin1")
    text += b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + bytes(16)


def npz_of_headers(arrays: dict[str, tuple[tuple[int, ...], str]]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, (shape, dtype) in arrays.items():
            zf.writestr(f"{name}.npy", npy_header_member(shape, dtype))
    return buffer.getvalue()


@pytest.mark.parametrize(
    ("arrays", "status", "words"),
    [
        ({"images": ((40, 2000, 2000, 3), "<f8")}, 413, ["'images'", "SFMNERF_MAX_ZIP_UNCOMPRESSED_BYTES"]),
        ({"images": ((2, 8000, 8000, 3), "|u1")}, 413, ["8000x8000", "SFMNERF_MAX_IMAGE_PIXELS"]),
        ({"images": ((2, 4, 4, 3), "O")}, 422, ["'images'", "Python objects"]),
        ({"../images": ((2, 4, 4, 3), "<f4")}, 422, ["'../images.npy'", "not a named .npy array"]),
    ],
    ids=["40x2000x2000x3-float64", "images-over-pixel-limit", "object-array", "member-path"],
)
def test_npz_arrays_are_capped_from_their_headers_before_decompression(
    client, settings, arrays, status, words
):
    response = post_dataset(client, "bomb.npz", npz_of_headers(arrays))
    detail = assert_refused(response, status, "dataset", "bomb.npz", *words)
    assert str(settings.data_dir) not in detail
    assert list(settings.jobs_dir.iterdir()) == []


def test_a_dataset_image_over_the_pixel_limit_answers_413_naming_it(tmp_path):
    """Pillow's limit is the setting's in the validation process (a 12000^2 PNG in the issue; 200^2 here)."""
    with TestClient(create_app(make_settings(tmp_path / "data", max_image_pixels=10_000))) as client:
        archive = blender_zip(["train/r_0"], {"train/r_0.png": png_bytes(200, 200)})
        detail = assert_refused(
            post_dataset(client, "big.zip", archive), 413, "r_0.png", "SFMNERF_MAX_IMAGE_PIXELS"
        )
        assert str(tmp_path) not in detail
        assert list((tmp_path / "data" / "jobs").iterdir()) == []


def test_a_dataset_that_needs_more_memory_than_the_validation_limit_answers_413(tmp_path):
    """30 x 1000^2 RGB bytes become 360 MB of float32 when loaded: over a 256 MB validation process."""
    settings = make_settings(tmp_path / "data", validation_memory_bytes=2**28)
    npz = io.BytesIO()
    poses = np.tile(np.eye(4), (30, 1, 1))
    np.savez_compressed(
        npz, images=np.zeros((30, 1000, 1000, 3), np.uint8), poses=poses, focal=np.array(100.0)
    )
    with TestClient(create_app(settings)) as client:
        response = post_dataset(client, "big.npz", npz.getvalue())
        assert_refused(response, 413, "dataset", "SFMNERF_VALIDATION_MEMORY_BYTES=268435456")
        assert list(settings.jobs_dir.iterdir()) == []


def test_an_npz_needing_more_memory_than_a_validation_process_has_is_refused_from_its_headers(
    client, settings, monkeypatch
):
    """40x2000x2000x3 zeros (the issue's 467 KB upload): 480 MB of bytes, within the zip limit, but ~6 GB
    once loaded; refused from the .npy header without starting a validation process."""
    import service.validation as validation

    started = []
    monkeypatch.setattr(validation, "_run_check", lambda *args: started.append(args))
    response = post_dataset(client, "zeros.npz", npz_of_headers({"images": ((40, 2000, 2000, 3), "|u1")}))
    assert_refused(response, 413, "dataset: zeros.npz", "MiB", "SFMNERF_VALIDATION_MEMORY_BYTES")
    assert started == [] and list(settings.jobs_dir.iterdir()) == []


def test_a_dataset_whose_image_headers_need_more_memory_is_refused_before_decoding(tmp_path, monkeypatch):
    """A 3000x3000 PNG (a few KB) takes ~290 MB while it is decoded: over a 256 MB validation process."""
    import service.validation as validation

    started = []
    monkeypatch.setattr(validation, "_run_check", lambda *args: started.append(args))
    names = ["train/r_0", "train/r_1"]
    archive = blender_zip(names, {"train/r_0.png": png_bytes(), "train/r_1.png": png_bytes(3000, 3000)})
    with TestClient(create_app(make_settings(tmp_path / "data", validation_memory_bytes=2**28))) as client:
        response = post_dataset(client, "big.zip", archive)
        assert_refused(response, 413, "dataset", "SFMNERF_VALIDATION_MEMORY_BYTES=268435456")
        assert started == [] and list((tmp_path / "data" / "jobs").iterdir()) == []


def test_the_default_validation_memory_is_a_few_hundred_mb_that_the_real_datasets_fit(shared_data, tmp_path):
    """lego_200 (100 views) and the 3072x2048 photos of Strecha's fountain as a dataset of 11 views."""
    from service.settings import ServiceSettings
    from service.validation import check_isolated

    settings = make_settings(tmp_path / "data")
    assert ServiceSettings.model_fields["validation_memory_bytes"].default <= 512 * 2**20
    lego = shared_data / "lego_200"
    check_isolated("dataset", {"path": str(lego), "field": "dataset", "within": str(lego)}, settings)
    fountain = tmp_path / "fountain"
    fountain.mkdir()
    photos = sorted((shared_data / "strecha" / "fountain-P11").glob("*.jpg"))
    frames = [{"file_path": f"./{p.stem}", "transform_matrix": np.eye(4).tolist()} for p in photos]
    for photo in photos:
        (fountain / f"{photo.stem}.png").write_bytes(photo.read_bytes())  # Pillow reads the JPEG inside
    (fountain / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    check_isolated("dataset", {"path": str(fountain), "field": "dataset", "within": str(tmp_path)}, settings)


def test_an_upload_finding_every_validation_slot_busy_answers_429_with_retry_after(tmp_path, monkeypatch):
    from service.validation import validation_slots

    settings = make_settings(tmp_path / "data", validation_workers=1)
    files = [("images", (f"{i}.png", png_bytes(), "image/png")) for i in (1, 2)]
    slots = validation_slots(1)
    with TestClient(create_app(settings)) as client:
        assert slots.acquire(blocking=False)  # another upload being checked
        try:
            response = client.post("/v1/reconstructions", files=files, data={"K": "1 0 4 0 1 4 0 0 1"})
        finally:
            slots.release()
        assert_refused(response, 429, "images", "SFMNERF_VALIDATION_WORKERS")
        assert int(response.headers["Retry-After"]) > 0
        assert list(settings.jobs_dir.iterdir()) == []
        # The slot free again, the same upload is checked and accepted.
        response = client.post("/v1/reconstructions", files=files, data={"K": "1 0 4 0 1 4 0 0 1"})
        assert response.status_code == 202


def test_a_decompression_bomb_in_a_reconstruction_upload_answers_413_and_leaves_no_folder(client, settings):
    """A PNG header claiming 15000^2 pixels (Pillow's DecompressionBombError) is a 413, not a 500."""
    small = png_bytes(8, 8)
    header = struct.pack(">II", 15000, 15000) + small[24:29]  # IHDR: width, height, then depth, type...
    bomb = small[:16] + header + struct.pack(">I", zlib.crc32(b"IHDR" + header)) + small[33:]
    files = [("images", ("1.png", png_bytes(), "image/png")), ("images", ("2.png", bomb, "image/png"))]
    response = client.post("/v1/reconstructions", files=files, data={"K": "1 0 4 0 1 4 0 0 1"})
    assert_refused(response, 413, "2.png", "SFMNERF_MAX_IMAGE_PIXELS")
    assert list(settings.jobs_dir.iterdir()) == []


def test_a_submission_failing_for_any_reason_leaves_no_folder(settings, monkeypatch):
    import service.actions.reconstructions as routes

    def broken(*_args, **_kwargs):
        raise RuntimeError("a bug while storing the inputs")

    monkeypatch.setattr(routes, "_store_inputs", broken)
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        files = [("images", (f"{i}.png", png_bytes(), "image/png")) for i in (1, 2)]
        assert client.post("/v1/reconstructions", files=files).status_code == 500
        assert list(settings.jobs_dir.iterdir()) == []


def test_orphan_job_folders_are_swept_at_start_up(settings):
    store = JobStore(settings.resolved_database_url)
    kept = store.create(JobKind.reconstruction, {}).id
    store.dispose()
    old = time.time() - 3600
    for name in ("a" * 32, kept):
        (job_dir(settings, name) / "input").mkdir(parents=True)
        os.utime(job_dir(settings, name), (old, old))
    (job_dir(settings, "b" * 32) / "input").mkdir(parents=True)  # fresh: maybe another server's upload
    with TestClient(create_app(settings)):
        assert sorted(p.name for p in settings.jobs_dir.iterdir()) == sorted([kept, "b" * 32])


# ---- 3. authentication before reading, clients and their jobs ----------------------------------------

ALICE, BOB, ADMIN = "alice-token-0123456789", "bob-token-0123456789", "admin-token-0123456789"


@pytest.fixture
def clients_settings(tmp_path):
    clients_file = tmp_path / "clients.txt"
    clients_file.write_text(
        "# name:sha256:HEX\n"
        + "".join(
            f"{name}:sha256:{hashlib.sha256(token.encode()).hexdigest()}\n"
            for name, token in [("alice", ALICE), ("bob", BOB)]
        )
    )
    return make_settings(tmp_path / "data", api_token=ADMIN, clients_file=clients_file)


@pytest.mark.parametrize(
    "line", ["alice:plaintext-token", f"admin:sha256:{'0' * 64}", f"alice:sha256:{'0' * 63}"]
)
def test_a_clients_file_holds_only_named_sha256_digests(tmp_path, line):
    from service.auth import read_clients_file

    path = tmp_path / "clients.txt"
    path.write_text(f"bob:sha256:{'1' * 64}\n{line}\n")
    with pytest.raises(ValueError, match=r"clients\.txt:2"):
        read_clients_file(path)


def test_a_request_without_a_token_is_refused_before_its_body_is_read(clients_settings):
    """A 300 MB upload without a token: 401 and the body never received (ASGI receive never called)."""
    app = create_app(clients_settings)
    scope = {
        "type": "http",
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": "/v1/reconstructions",
        "raw_path": b"/v1/reconstructions",
        "query_string": b"",
        "root_path": "",
        "headers": [
            (b"host", b"localhost"),
            (b"content-type", b"multipart/form-data; boundary=x"),
            (b"content-length", b"314572800"),
        ],
        "client": ("127.0.0.1", 1),
        "server": ("127.0.0.1", 80),
    }
    received, sent = [], []

    async def receive():
        received.append(True)
        return {"type": "http.request", "body": b"x" * 2**20, "more_body": True}

    async def send(message):
        sent.append(message)

    asyncio.run(app(scope, receive, send))
    assert sent[0]["status"] == 401 and received == []


def test_invalid_json_without_a_token_is_401_and_a_large_json_body_is_413(clients_settings):
    with TestClient(create_app(clients_settings)) as client:
        response = client.post(
            f"/v1/nerf/{UNKNOWN_ID}/render",
            content=b"{not json",
            headers={"Content-Type": "application/json"},
        )
        assert response.status_code == 401
        big = json.dumps({"c2w": [[0.0] * 4] * 4, "width": 8, "height": 8, "pad": "x" * 2_000_000})
        response = client.post(
            f"/v1/nerf/{UNKNOWN_ID}/render",
            content=big,
            headers={"Content-Type": "application/json", "Authorization": f"Bearer {ALICE}"},
        )
        assert_refused(response, 413, "SFMNERF_MAX_JSON_BYTES=1048576")


@pytest.mark.parametrize(
    ("docs", "without", "with_token"), [("token", 401, 200), ("public", 200, 200), ("off", 401, 404)]
)
def test_docs_and_schema_follow_the_setting(clients_settings, docs, without, with_token):
    with TestClient(create_app(clients_settings.model_copy(update={"docs": docs}))) as client:
        for path in ("/docs", "/redoc", "/openapi.json"):
            assert client.get(path).status_code == without, path
            assert client.get(path, headers={"Authorization": f"Bearer {ADMIN}"}).status_code == with_token


def finished_job(store: JobStore, kind: JobKind, owner: str, source: str | None = None) -> str:
    job = store.create(kind, {}, owner=owner, source_job_id=source)
    attempt = store.claim(job.id, worker="test")
    store.finish(job.id, attempt, JobState.succeeded, result={})
    return job.id


def alices_scene(store: JobStore, reconstruction_id: str) -> str:
    """A failed scene whose reconstruction job (alice's) makes it alice's."""
    scene = Scene(
        id=new_job_id(),
        state=JobState.failed,
        stage="reconstruction",
        params={},
        reconstruction_job_id=reconstruction_id,
        log=[],
    )
    return store.create_scene(scene).id


def test_a_client_sees_none_of_another_clients_jobs_on_any_path_of_the_schema(clients_settings):
    store = JobStore(clients_settings.resolved_database_url)
    jobs = {kind: finished_job(store, kind, "alice") for kind in (JobKind.reconstruction, JobKind.nerf)}
    jobs[JobKind.video] = finished_job(store, JobKind.video, "alice", source=jobs[JobKind.nerf])
    scene_id = alices_scene(store, jobs[JobKind.reconstruction])
    store.dispose()
    alice, bob, admin = ({"Authorization": f"Bearer {token}"} for token in (ALICE, BOB, ADMIN))
    bodies = {
        "render": {"c2w": np.eye(4).tolist(), "width": 8, "height": 8},
        "video": {"num_frames": 2, "width": 8, "height": 8},
    }
    with TestClient(create_app(clients_settings)) as client:
        schema = client.get("/openapi.json", headers=bob).json()
        walked = 0
        for path, operations in schema["paths"].items():
            if "{job_id}" not in path:
                continue
            kind = JobKind.nerf if path.startswith("/v1/nerf") else JobKind.reconstruction
            url = path.format(job_id=jobs[kind], step=1, name="a.png")
            for method in operations:
                body = bodies.get(path.rsplit("/", 1)[-1]) if method == "post" else None
                response = client.request(method, url, headers=bob, json=body)
                assert response.status_code == 404, f"{method} {url}: {response.status_code} {response.text}"
                assert response.json()["detail"] == f"job {jobs[kind]} not found"
                walked += 1
        assert walked >= 18  # with PUT and DELETE /v1/jobs/{job_id}/pin
        walked = 0
        for path, operations in schema["paths"].items():  # alice's scene: 404 for bob on every route
            if "{scene_id}" not in path:
                continue
            for method in operations:
                response = client.request(method, path.format(scene_id=scene_id, name="a.png"), headers=bob)
                assert response.status_code == 404, f"{method} {path}: {response.status_code} {response.text}"
                assert response.json()["detail"] == f"scene {scene_id} not found"
                walked += 1
        assert walked >= 5
        for who, total in ((bob, 0), (alice, 1), (admin, 1)):
            assert client.get("/v1/scenes", headers=who).json()["total"] == total
        assert client.get(f"/v1/scenes/{scene_id}", headers=alice).status_code == 200
        for path, operations in schema["paths"].items():  # and without a token, every path but health: 401
            url = path.format(job_id=jobs[JobKind.nerf], scene_id=scene_id, step=1, name="a.png")
            for method in operations:
                expected = 200 if path in ("/healthz", "/readyz") else 401
                assert client.request(method, url).status_code == expected, f"{method} {url}"
        for who in (alice, admin):  # the owner and the admin still see it (the deletes above were refused)
            assert client.get(f"/v1/jobs/{jobs[JobKind.nerf]}", headers=who).status_code == 200
        assert client.get("/v1/jobs", headers=bob).json()["total"] == 0
        assert client.get("/v1/jobs", headers=alice).json()["total"] == 3
        assert client.get("/v1/jobs", headers=admin).json()["total"] == 3
        refused = client.post(
            "/v1/nerf", data={"reconstruction_id": jobs[JobKind.reconstruction]}, headers=bob
        )
        assert_refused(refused, 404, jobs[JobKind.reconstruction])
        assert client.get("/v1/jobs", headers={"Authorization": "Bearer nobody"}).status_code == 401


def test_a_job_records_the_client_that_created_it(clients_settings):
    with TestClient(create_app(clients_settings)) as client:
        files = [("images", (f"{i}.png", png_bytes(), "image/png")) for i in (1, 2)]
        bob = {"Authorization": f"Bearer {BOB}"}
        response = client.post(
            "/v1/reconstructions", files=files, data={"K": "8 0 4 0 8 4 0 0 1"}, headers=bob
        )
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        assert (
            client.get(f"/v1/jobs/{job_id}", headers={"Authorization": f"Bearer {ALICE}"}).status_code == 404
        )
        client.post(f"/v1/jobs/{job_id}/cancel", headers=bob)
        assert client.app.state.store.get(job_id).owner == "bob"


# ---- 5. webhooks ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:9/hook",
        "http://[::1]:9/hook",
        "http://localhost:9/hook",
        "http://2130706433:9/hook",
        "http://0x7f.1:9/hook",
        "http://127.1:9/hook",
        "http://[::ffff:127.0.0.1]:9/hook",
        "http://169.254.169.254/latest/meta-data",
        "http://10.1.2.3/hook",
        "http://192.168.0.1/hook",
        "http://0.0.0.0:9/hook",
        "http://224.0.0.1/hook",
        "http://240.0.0.1/hook",
        "http://user:pw@93.184.216.34/hook",
    ],
)
def test_webhooks_to_internal_addresses_or_with_credentials_are_refused_naming_the_field(client, url):
    response = client.post("/v1/nerf", data={"reconstruction_id": UNKNOWN_ID, "webhook_url": url})
    detail = assert_refused(response, 422, "webhook_url")
    assert "pw" not in detail


def test_the_allow_list_permits_a_loopback_webhook(tmp_path):
    from service.webhooks import check_url

    settings = make_settings(tmp_path, webhook_allowed_networks=["127.0.0.0/8", "::1/128"])
    for url in ("http://127.0.0.1:9/hook", "http://localhost:9/hook", "http://[::ffff:127.0.0.1]:9/x"):
        assert check_url(url, settings) == url


def test_a_webhook_goes_to_the_address_checked_with_one_resolution_and_its_host_header(tmp_path, monkeypatch):
    from service import webhooks

    receiver = WebhookReceiver()
    lookups = []
    real_getaddrinfo = socket.getaddrinfo

    def counting_getaddrinfo(host, *args, **kwargs):
        lookups.append(host)
        return real_getaddrinfo("127.0.0.1" if host == "hooks.example" else host, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", counting_getaddrinfo)
    settings = make_settings(tmp_path, webhook_attempts=1, webhook_allowed_networks=["127.0.0.0/8"])
    try:
        assert webhooks.deliver(f"http://hooks.example:{receiver.port}/done?x=1", "{}", settings)
        # The name was resolved once; the connection went to the checked address (a literal, no DNS).
        assert lookups == ["hooks.example", "127.0.0.1"]
        assert receiver.requests == [
            {"path": "/done?x=1", "host": f"hooks.example:{receiver.port}", "body": b"{}"}
        ]
    finally:
        receiver.close()


def test_a_webhook_redirect_is_not_followed(tmp_path):
    from service import webhooks

    target = WebhookReceiver()
    redirecting = WebhookReceiver(status=307, location=f"http://127.0.0.1:{target.port}/elsewhere")
    settings = make_settings(tmp_path, webhook_attempts=1, webhook_allowed_networks=["127.0.0.0/8"])
    try:
        assert not webhooks.deliver(f"http://127.0.0.1:{redirecting.port}/hook", "{}", settings)
        assert len(redirecting.requests) == 1 and target.requests == []
    finally:
        target.close()
        redirecting.close()


def failing_job_files(shared_data: Path) -> list:
    """Two copies of one small photo: a reconstruction that fails within a second or two (no parallax)."""
    photo = io.BytesIO()
    Image.open(shared_data / "unity_hall" / "1.png").reduce(4).save(photo, format="PNG")
    return [("images", (f"{i}.png", photo.getvalue(), "image/png")) for i in (1, 2)]


def test_a_webhook_that_never_answers_does_not_hold_the_next_job(tmp_path, shared_data):
    """Concurrency 1; job A's webhook accepts the connection and never answers (10 s timeout x 3 attempts):
    job B still runs as soon as A ends, and A's log says only 'webhook failed' in the end."""
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(8)  # connections complete in the backlog; nothing ever reads or answers
    url = f"http://127.0.0.1:{silent.getsockname()[1]}/hook"
    settings = make_settings(
        tmp_path / "data", webhook_allowed_networks=["127.0.0.0/8"], webhook_timeout_seconds=10.0
    )
    try:
        with TestClient(create_app(settings)) as client:
            files = failing_job_files(shared_data)
            data = {"features": "sift", "K": "180 0 100 0 180 75 0 0 1"}
            first = client.post("/v1/reconstructions", files=files, data={**data, "webhook_url": url})
            second = client.post("/v1/reconstructions", files=files, data=data)
            assert first.status_code == second.status_code == 202, (first.text, second.text)
            a = wait_for_job(client, first.json()["id"])
            b = wait_for_job(client, second.json()["id"])
            assert a["state"] == b["state"] == "failed"
            waited = datetime.fromisoformat(b["started_at"]) - datetime.fromisoformat(a["finished_at"])
            assert 0 <= waited.total_seconds() < settings.webhook_timeout_seconds  # B followed A at once
            a_lines = client.get(f"/v1/jobs/{a['id']}/logs").json()["lines"]
            assert not any(
                line.startswith("webhook") for line in a_lines
            )  # still waiting for the silent host
    finally:
        silent.close()


# ---- 9. no internals in answers ---------------------------------------------------------------------


def test_a_job_error_names_no_server_path_and_its_log_holds_no_traceback(settings, monkeypatch):
    from service import runner

    store = JobStore(settings.resolved_database_url)
    job = store.create(JobKind.reconstruction, {})
    inputs = job_dir(settings, job.id) / "input" / "1.png"

    def crash(_context):
        raise RuntimeError(f"cannot open {inputs}")

    monkeypatch.setitem(runner.JOB_FUNCTIONS, JobKind.reconstruction, crash)
    attempt = store.claim(job.id, worker="test")
    assert execute(store, job.id, attempt, settings) == JobState.failed
    finished = store.get(job.id)
    assert finished.error == "RuntimeError: cannot open 1.png"
    lines = store.read_logs(job.id, 0, 100)
    assert not any("Traceback" in line or str(settings.data_dir) in line for line in lines), lines
    store.dispose()


def test_cuda_on_a_machine_without_a_gpu_answers_422_naming_device(client):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    response = client.post("/v1/nerf", data={"reconstruction_id": UNKNOWN_ID, "device": "cuda"})
    assert_refused(response, 422, "device", "cuda")
