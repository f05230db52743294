"""One reconstruction spread over two real Celery workers (a real redis-server) gives what one process
gives: the same keypoints, matches, registered images and poses."""

from __future__ import annotations

import json
import math
import pickle
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from estimation import ReconstructionConfig, reconstruct
from estimation.config import SiftConfig
from estimation.errors import InputError
from estimation.features.sift import extract_chunk
from service.app import create_app
from service.celery_config import SPREAD_TASK, make_celery
from service.layout import SPREAD_DIR, job_dir, output_dir
from service.spread import EXTRACTION, STAGE_FILE, CeleryStages, Stage, spread_folder
from service.store import JobStore
from tests.service.conftest import make_settings, wait_for_job
from tests.service.test_celery import broker_url, start_worker, stop_worker, worker_env  # noqa: F401

LEGO_IMAGES = 24
LEGO_SIDE = 200
SPREAD_SETTINGS = {
    "SFMNERF_SPREAD_MIN_IMAGES": "10",
    "SFMNERF_SPREAD_IMAGES_PER_CHUNK": "3",
    "SFMNERF_SPREAD_PAIRS_PER_BLOCK": "25",
}
"""Small chunks, so that 24 images make 8 extraction chunks and 276 pairs a dozen matching blocks."""
POSE_TOLERANCE = 1e-6
WORKER_START_SECONDS = 120.0


def lego_files(shared_data: Path) -> tuple[list, str]:
    """lego_200's first training view and the LEGO_IMAGES - 1 training views nearest to it (the views of
    one side of the object, which overlap) as upload files, and their K."""
    folder = shared_data / "lego_200"
    frames = json.loads((folder / "transforms_train.json").read_text())
    focal = 0.5 * LEGO_SIDE / math.tan(0.5 * frames["camera_angle_x"])
    centre = (LEGO_SIDE - 1) / 2
    centres = np.array([np.array(frame["transform_matrix"])[:3, 3] for frame in frames["frames"]])
    nearest = np.argsort(np.linalg.norm(centres - centres[0], axis=1), kind="stable")[:LEGO_IMAGES]
    paths = [folder / f"{frames['frames'][index]['file_path']}.png" for index in nearest]
    files = [("images", (path.name, path.read_bytes(), "image/png")) for path in paths]
    return files, f"{focal} 0 {centre} 0 {focal} {centre} 0 0 1"


def wait_until_every_worker_works(settings, queues: list[str], image: Path) -> None:
    """Returns once a worker process serving each queue has run a task (each extracts `image` for a probe
    stage): workers import their libraries before their first task, and one still importing would leave
    every chunk to the other."""
    probe = spread_folder(settings, "probe", 1)
    (probe / EXTRACTION).mkdir(parents=True)
    shutil.copy(image, probe.parents[1] / image.name)
    stage = Stage(SiftConfig(), [[Path(image.name)]] * len(queues))
    (probe / EXTRACTION / STAGE_FILE).write_bytes(pickle.dumps(stage))
    celery = make_celery(settings)
    for index, queue in enumerate(queues):
        celery.send_task(SPREAD_TASK, args=["probe", 1, EXTRACTION, index], queue=queue)
    deadline = time.monotonic() + WORKER_START_SECONDS
    while not all((probe / EXTRACTION / f"{index}.pickle").exists() for index in range(len(queues))):
        assert time.monotonic() < deadline, "the workers did not start"
        time.sleep(0.2)


def pose_table(report: dict) -> dict[str, np.ndarray]:
    """Each registered image's [R | t] (world to camera)."""
    return {camera["image"]: np.hstack([camera["R"], np.reshape(camera["t"], (3, 1))])
            for camera in report["cameras"]}


def test_a_reconstruction_spread_over_two_celery_workers_equals_one_process(
        tmp_path, broker_url, shared_data):  # noqa: F811
    settings = make_settings(tmp_path / "data", executor="celery", broker_url=broker_url)
    files, K = lego_files(shared_data)
    with TestClient(create_app(settings)) as client:
        env = {**worker_env(settings), **SPREAD_SETTINGS}
        own_queues = [f"probe-{number}" for number in range(2)]
        workers = [start_worker(env, queues=f"celery,{queue}") for queue in own_queues]
        try:
            wait_until_every_worker_works(settings, own_queues, shared_data / "lego_200/train/r_0.png")
            upload = client.post("/v1/reconstructions", files=files, data={"K": K, "features": "sift"})
            job_id = upload.json()["id"]
            job = wait_for_job(client, job_id, timeout=400)
            lines = client.get(f"/v1/jobs/{job_id}/logs").json()["lines"]
        finally:
            for worker in workers:
                stop_worker(worker)
    assert job["state"] == "succeeded", lines
    # Both workers computed chunks of each stage; the stages' files are gone once the job ended.
    assert any("extraction: 8 chunks done by 2 worker processes" in line for line in lines), lines
    assert any("matching: " in line and "done by 2 worker processes" in line for line in lines), lines
    assert not (job_dir(settings, job_id) / SPREAD_DIR).exists()

    store = JobStore(settings.resolved_database_url)
    try:
        config = ReconstructionConfig.model_validate(store.get(job_id).params["config"])
    finally:
        store.dispose()
    spread = json.loads((output_dir(settings, job_id) / "report.json").read_text())
    single = reconstruct(job_dir(settings, job_id) / "input", tmp_path / "single", config).report

    for counts in ("keypoints_per_image", "matches_per_pair", "verified_matches_per_pair"):
        assert spread["features"][counts] == single["features"][counts], counts
    assert spread["features"]["tracks"] == single["features"]["tracks"]
    assert spread["images_registered"] >= LEGO_IMAGES - 4
    spread_poses, single_poses = pose_table(spread), pose_table(single)
    assert spread_poses.keys() == single_poses.keys()
    for image, pose in single_poses.items():
        np.testing.assert_allclose(spread_poses[image], pose, atol=POSE_TOLERANCE, err_msg=image)


def test_without_other_workers_the_job_does_every_chunk_and_a_chunks_error_is_its_own(
        tmp_path, broker_url, shared_data):  # noqa: F811
    # A broker database of its own: no worker takes these tasks.
    settings = make_settings(tmp_path / "data", executor="celery",
                             broker_url=broker_url.rsplit("/", 1)[0] + "/3")
    inputs = job_dir(settings, "job") / "input"
    inputs.mkdir(parents=True)
    for name in ("r_0.png", "r_1.png"):
        shutil.copy(shared_data / "lego_200/train" / name, inputs / name)
    (inputs / "broken.png").write_bytes(b"not a png")
    lines: list[str] = []
    stages = CeleryStages(settings, "job", 1, lines.append)
    detected = [image for chunk in stages.extract([[inputs / "r_0.png"], [inputs / "r_1.png"]], SiftConfig())
                for image in chunk]
    assert [len(features.uv) for features, _ in detected] == [
        len(extract_chunk([inputs / name], SiftConfig())[0][0].uv) for name in ("r_0.png", "r_1.png")]
    assert len(lines) == 1 and lines[0].startswith("extraction: 2 chunks done by 1 worker processes (CPU")
    with pytest.raises(InputError, match="broken.png: not a readable PNG/JPEG image"):
        list(stages.extract([[inputs / "r_0.png"], [inputs / "broken.png"]], SiftConfig()))
    stages.close()
    assert not (job_dir(settings, "job") / SPREAD_DIR).exists()
