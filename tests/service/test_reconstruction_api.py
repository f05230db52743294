"""End to end through the API: upload Unity Hall, the job succeeds, and every result agrees with the CLI's."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from fastapi.testclient import TestClient

from service.app import create_app
from service.cli import main as cli
from tests.service.conftest import (
    WebhookReceiver,
    capture_reconstruction_config,
    make_settings,
    unity_hall_files,
    wait_for_job,
)


@pytest.fixture(scope="module")
def webhook_receiver():
    receiver = WebhookReceiver()
    yield receiver
    receiver.close()


@pytest.fixture(scope="module")
def api(tmp_path_factory, shared_data, webhook_receiver):
    """One app for the module and one finished Unity Hall job: (client, job, settings)."""
    settings = make_settings(
        tmp_path_factory.mktemp("api") / "data", webhook_allowed_networks=["127.0.0.0/8"]
    )
    with TestClient(create_app(settings)) as client:
        response = client.post(
            "/v1/reconstructions",
            files=unity_hall_files(shared_data / "unity_hall"),
            data={"webhook_url": webhook_receiver.url},
        )
        assert response.status_code == 202, response.text
        assert response.headers["Location"] == f"/v1/jobs/{response.json()['id']}"
        job = wait_for_job(client, response.json()["id"])
        assert job["state"] == "succeeded", client.get(f"/v1/jobs/{job['id']}/logs").json()
        # The webhook is delivered after the job ends and logs a line of its own: wait for it, so that
        # every test of the module reads the same, final log.
        wait_for_job(client, job["id"], until=lambda _: _webhook_logged(client, job["id"]))
        yield client, job, settings


def _webhook_logged(client: TestClient, job_id: str) -> bool:
    lines = client.get(f"/v1/jobs/{job_id}/logs").json()["lines"]
    return any(line.startswith("webhook ") for line in lines)


@pytest.fixture(scope="module")
def cli_out(tmp_path_factory, shared_data) -> Path:
    """What `sfmnerf reconstruct` writes for the same input."""
    out = tmp_path_factory.mktemp("cli") / "out"
    result = CliRunner().invoke(cli, ["reconstruct", str(shared_data / "unity_hall"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_the_job_reports_progress_stages_and_a_summary(api):
    client, job, _ = api
    assert job["progress"] == 1.0 and job["finished_at"] and job["attempt"] == 1
    assert job["result"]["registered_images"] >= 3 and job["result"]["points"] > 100
    lines = client.get(f"/v1/jobs/{job['id']}/logs").json()["lines"]
    job_lines = [line for line in lines if not line.startswith("webhook ")]
    assert any(line.startswith("stage:") for line in lines)
    assert job_lines[-1].startswith("finished: succeeded")
    page = client.get(f"/v1/jobs/{job['id']}/logs?offset=2").json()
    assert page["lines"] == lines[2:] and page["next_offset"] == len(lines)


def test_poses_agree_with_the_cli(api, cli_out):
    client, job, _ = api
    body = client.get(f"/v1/reconstructions/{job['id']}").json()
    report = json.loads((cli_out / "report.json").read_text())
    assert np.allclose(body["intrinsics"]["K"], report["intrinsics"]["K"])
    assert [c["image"] for c in body["cameras"]] == [c["image"] for c in report["cameras"]]
    for mine, theirs in zip(body["cameras"], report["cameras"], strict=True):
        for key in ("R", "t", "C"):
            assert np.allclose(mine[key], theirs[key], atol=1e-6), (mine["image"], key)
        R, t = np.array(mine["R"]), np.array(mine["t"])
        assert np.allclose(-R.T @ t, mine["C"], atol=1e-6)
    assert body["unregistered"] == report["unregistered"]
    assert body["statistics"] and "intrinsics" not in body["statistics"]
    assert set(body["files"]) >= {"points.ply", "colmap.zip", "transforms.json"}


def test_points_ply_is_the_cli_point_cloud(api, cli_out):
    client, job, _ = api
    response = client.get(f"/v1/reconstructions/{job['id']}/points.ply")
    assert response.status_code == 200
    assert response.content == (cli_out / "points.ply").read_bytes()


def test_colmap_zip_holds_the_cli_text_model(api, cli_out):
    client, job, _ = api
    response = client.get(f"/v1/reconstructions/{job['id']}/colmap.zip")
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(response.content)) as zf:
        names = set(zf.namelist())
        assert names == {f"sparse/{p.name}" for p in (cli_out / "sparse").iterdir()}
        assert {"sparse/cameras.txt", "sparse/images.txt", "sparse/points3D.txt"} <= names
        for name in names:
            assert zf.read(name) == (cli_out / name).read_bytes(), name


def test_transforms_json_has_the_cli_cameras(api, cli_out):
    client, job, _ = api
    mine = client.get(f"/v1/reconstructions/{job['id']}/transforms.json").json()
    theirs = json.loads((cli_out / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        assert mine[key] == pytest.approx(theirs[key])
    assert [Path(f["file_path"]).name for f in mine["frames"]] == [
        Path(f["file_path"]).name for f in theirs["frames"]
    ]
    for a, b in zip(mine["frames"], theirs["frames"], strict=True):
        assert np.allclose(a["transform_matrix"], b["transform_matrix"], atol=1e-6)


def test_figures_are_served_and_unknown_ones_are_404(api):
    client, job, _ = api
    figures = [
        name
        for name in client.get(f"/v1/reconstructions/{job['id']}").json()["files"]
        if name.startswith("figures/")
    ]
    assert figures
    response = client.get(f"/v1/reconstructions/{job['id']}/{figures[0]}")
    assert response.status_code == 200 and response.content.startswith(b"\x89PNG")
    assert client.get(f"/v1/reconstructions/{job['id']}/figures/nope.png").status_code == 404
    assert client.get(f"/v1/reconstructions/{job['id']}/figures/..%2F..%2Freport.json").status_code == 404


def test_the_webhook_got_the_finished_job(api, webhook_receiver):
    _, job, _ = api
    deliveries = [body for body in webhook_receiver.bodies() if body["id"] == job["id"]]
    assert deliveries and deliveries[-1]["state"] == "succeeded"


def test_jobs_are_listed_and_filtered(api):
    client, job, _ = api
    listing = client.get("/v1/jobs?kind=reconstruction&state=succeeded").json()
    assert job["id"] in [item["id"] for item in listing["items"]]
    assert client.get("/v1/jobs?kind=nerf").json()["total"] == 0


def test_a_finished_job_cannot_be_cancelled_or_retried_and_is_not_a_nerf_job(api):
    client, job, _ = api
    assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 409
    assert client.post(f"/v1/jobs/{job['id']}/retry").status_code == 409
    assert client.get(f"/v1/nerf/{job['id']}").status_code == 404


def test_delete_removes_the_job_and_its_files(api, shared_data):
    client, _, settings = api
    created = client.post("/v1/reconstructions", files=unity_hall_files(shared_data / "unity_hall")).json()
    folder = settings.jobs_dir / created["id"]
    assert folder.is_dir()
    unfinished = client.post("/v1/nerf", data={"reconstruction_id": created["id"], "steps": "1"})
    assert unfinished.status_code == 409 and created["id"] in unfinished.json()["detail"]
    assert client.delete(f"/v1/jobs/{created['id']}").status_code == 204
    assert client.get(f"/v1/jobs/{created['id']}").status_code == 404
    assert not folder.exists()


def test_a_nerf_job_can_train_on_the_finished_reconstruction(api):
    client, job, _ = api
    response = client.post(
        "/v1/nerf", data={"reconstruction_id": job["id"], "model": "vanilla", "steps": "5"}
    )
    assert response.status_code == 202, response.text
    nerf = response.json()
    assert nerf["kind"] == "nerf" and nerf["source_job_id"] == job["id"]
    assert client.post(f"/v1/jobs/{nerf['id']}/cancel").status_code == 200
    assert wait_for_job(client, nerf["id"], timeout=10)["state"] == "cancelled"


@pytest.mark.parametrize(("requested", "job_threads", "expected"), [(0, 1, 1), (0, 3, 3), (2, 1, 2)])
def test_a_job_asking_for_all_cores_gets_its_share_of_them(monkeypatch, tmp_path, requested, job_threads,
                                                           expected):
    from types import SimpleNamespace

    import estimation
    from service.params import ReconstructionParams
    from service.runner import run_reconstruction

    seen = capture_reconstruction_config(monkeypatch)
    context = SimpleNamespace(
        params=ReconstructionParams(config={"sift": {"workers": requested}}), input_dir=tmp_path / "in",
        output_dir=tmp_path / "out", progress=None, settings=make_settings(tmp_path, job_threads=job_threads),
    )
    with pytest.raises(estimation.InputError):
        run_reconstruction(context)
    assert [config.sift.workers for config in seen] == [expected]
