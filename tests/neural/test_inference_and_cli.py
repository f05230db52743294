"""Rendering, evaluation and the `sfmnerf nerf` commands on a tiny trained run."""

import json
import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from neural.config import TrainConfig
from neural.evaluation import evaluate, psnr, ssim
from neural.inference import look_at, orbit_poses, render_view
from neural.training import train
from service.cli import main
from tests.neural.conftest import TINY_VANILLA


@pytest.fixture(scope="module")
def tiny_run(tiny_npz, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "run"
    config = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=2, batch_rays=32, device="cpu")
    train(tiny_npz, run, config)
    return run


def test_psnr_and_ssim_closed_forms():
    rng = np.random.default_rng(0)
    image = rng.random((32, 32, 3))
    assert psnr(image + 0.1, image) == pytest.approx(20.0)
    assert ssim(image, image) == pytest.approx(1.0)
    assert ssim(rng.random((32, 32, 3)), image) < 0.2


def test_look_at_is_rigid_and_centre_ray_hits_the_target():
    c2w = look_at(np.array([3.0, 1.0, 2.0]), np.array([0.0, 0.5, 0.0]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
    towards = np.array([0.0, 0.5, 0.0]) - c2w[:3, 3]
    np.testing.assert_allclose(-c2w[:3, 2], towards / np.linalg.norm(towards))


def test_orbit_circles_the_target_at_constant_radius_and_elevation():
    orbit = {"target": [0.0, 0.0, 0.5], "up": [0.0, 0.0, 1.0], "radius": 4.0}
    poses = orbit_poses(orbit, 8, elevation_deg=30.0)
    offsets = poses[:, :3, 3] - np.array(orbit["target"])
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=1), 4.0)
    np.testing.assert_allclose(offsets[:, 2], 4.0 * math.sin(math.radians(30.0)))
    assert len({tuple(np.round(p, 6)) for p in poses[:, :3, 3]}) == 8


def test_render_view_matches_requested_size_and_changes_with_pose(tiny_run, tiny_npz):
    poses = np.load(tiny_npz)["poses"]
    first = render_view(tiny_run, poses[0], width=12, height=8, fov_x=0.69)
    second = render_view(tiny_run, poses[3], width=12, height=8, fov_x=0.69)
    assert first.shape == (8, 12, 3) and first.dtype == np.uint8
    assert not np.array_equal(first, second)


def test_evaluate_reports_each_validation_image(tiny_run, tiny_npz):
    result = evaluate(tiny_run, tiny_npz, "val")
    assert [m.name for m in result.per_image] == ["tiny[5]"]
    assert result.mean_psnr == pytest.approx(result.per_image[0].psnr)
    assert 0 < result.mean_psnr < 40 and -1 <= result.mean_ssim <= 1


def test_chunk_size_does_not_change_the_render(tiny_run, tiny_npz):
    from neural.inference import PinholeIntrinsics, load_run, render_image

    run = load_run(tiny_run)
    pose = torch.as_tensor(np.load(tiny_npz)["poses"][0])
    camera = PinholeIntrinsics(10, 10, 70.0, 70.0, 5.0, 5.0)
    whole = render_image(run.model, pose, camera, run.scene, run.background, chunk_rays=1000)
    chunked = render_image(run.model, pose, camera, run.scene, run.background, chunk_rays=7)
    torch.testing.assert_close(whole.rgb, chunked.rgb)


def test_cli_train_render_eval(tiny_npz, tmp_path):
    runner = CliRunner()
    run = tmp_path / "run"
    result = runner.invoke(
        main,
        ["nerf", "train", str(tiny_npz), "--out", str(run), "--steps", "2",
         "--batch-rays", "16", "--device", "cpu", "--seed", "1"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "trained 2 steps" in result.output
    assert json.loads((run / "config.json").read_text())["train"]["model"] == "fast"  # the default
    result = runner.invoke(
        main, ["nerf", "train", str(tiny_npz), "--out", str(run), "--resume", "--steps", "3"]
    )
    assert result.exit_code == 0, result.output
    assert "trained 3 steps" in result.output

    poses = np.load(tiny_npz)["poses"]
    transforms = {
        "camera_angle_x": 0.69,
        "frames": [
            {"file_path": "./test/r_9", "transform_matrix": poses[0].tolist()},
            {"file_path": "./test/r_19", "transform_matrix": poses[1].tolist()},
        ],
    }
    (tmp_path / "poses.json").write_text(json.dumps(transforms))
    renders = tmp_path / "renders"
    result = runner.invoke(
        main,
        ["nerf", "render", str(run), "--poses", str(tmp_path / "poses.json"), "--out", str(renders),
         "--width", "12", "--height", "10", "--depth"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in renders.iterdir()) == [
        "r_19.png",
        "r_19_depth.png",
        "r_9.png",
        "r_9_depth.png",
    ]
    assert Image.open(renders / "r_9.png").size == (12, 10)

    orbit = tmp_path / "orbit"
    result = runner.invoke(
        main, ["nerf", "render", str(run), "--orbit", "3", "--out", str(orbit), "--width", "8"]
    )
    assert result.exit_code == 0, result.output
    assert (orbit / "orbit.gif").is_file() and len(list(orbit.glob("orbit_*.png"))) == 3

    result = runner.invoke(main, ["nerf", "eval", str(run), "--data", str(tiny_npz), "--split", "val"])
    assert result.exit_code == 0, result.output
    assert "mean" in result.output
    report = json.loads((run / "eval_val.json").read_text())
    assert report["step"] == 3 and len(report["per_image"]) == 1


def test_cli_reports_bad_input_without_a_traceback(tmp_path, tiny_run):
    runner = CliRunner()
    (tmp_path / "bad.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [{"file_path": "a"}]}))
    result = runner.invoke(
        main,
        [
            "nerf",
            "render",
            str(tiny_run),
            "--poses",
            str(tmp_path / "bad.json"),
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert result.exit_code == 1 and "frames[0]: missing key 'transform_matrix'" in result.output
    result = runner.invoke(main, ["nerf", "eval", str(tmp_path), "--data", str(tmp_path)])
    assert result.exit_code == 1 and "not a training run" in result.output
    (tmp_path / "data").mkdir()
    result = runner.invoke(main, ["nerf", "train", str(tmp_path / "data"), "--out", str(tmp_path / "r")])
    assert result.exit_code == 1 and "not a dataset folder" in result.output
    result = runner.invoke(main, ["nerf", "render", str(tiny_run), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "exactly one of --poses" in result.output


def test_reconstruction_runs_take_poses_in_the_original_frame(tmp_path):
    from neural.data import load_dataset
    from neural.inference import PinholeIntrinsics, load_run, render_image
    from tests.neural.test_data import write_reconstruction

    _, original_poses, _ = write_reconstruction(tmp_path / "sfm")
    config = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=1, batch_rays=16, device="cpu")
    train(tmp_path / "sfm", tmp_path / "run", config)
    dataset = load_dataset(tmp_path / "sfm")
    run = load_run(tmp_path / "run")
    camera = PinholeIntrinsics(16, 12, 20.0, 20.0, 8.0, 6.0)
    expected = render_image(
        run.model, torch.as_tensor(dataset.poses[2]), camera, run.scene, run.background, 64
    )
    transforms = json.loads((tmp_path / "sfm/transforms.json").read_text())
    c2w_original = np.array(transforms["frames"][2]["transform_matrix"])
    np.testing.assert_allclose(c2w_original[:3, 3], original_poses[2].center, atol=1e-6)
    rendered = render_view(tmp_path / "run", c2w_original, 16, 12, fx=20.0).astype(int)
    assert np.abs(rendered - (expected.rgb.numpy() * 255 + 0.5).astype(int)).max() <= 1
    # the run converts with a real (non-identity) similarity, the same the dataset used
    np.testing.assert_allclose(run.normalization.pose_to_scene(c2w_original), dataset.poses[2], atol=1e-5)
    assert np.linalg.norm(c2w_original[:3, 3] - dataset.poses[2][:3, 3]) > 1.0


def test_render_intrinsics_follow_the_transforms_file_scaled_to_the_requested_size():
    from neural.inference import PinholeIntrinsics
    from service.commands.nerf import camera_for_transforms

    default = PinholeIntrinsics(400, 300, 999.0, 999.0, 200.0, 150.0)
    sfm = {"fl_x": 530.0, "fl_y": 532.0, "cx": 407.5, "cy": 313.5, "w": 800, "h": 600}
    camera = camera_for_transforms(default, sfm, "t.json")
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (265.0, 266.0, 203.75, 156.75)
    blender = camera_for_transforms(default, {"camera_angle_x": 2 * math.atan(0.5)}, "t.json")
    assert blender.fx == pytest.approx(400.0) and (blender.cx, blender.cy) == (200.0, 150.0)
    with pytest.raises(ValueError, match="'fl_x' needs 'w'"):
        camera_for_transforms(default, {"fl_x": 10.0}, "t.json")


def test_cli_photo_options_are_recorded_and_eval_and_render_default_to_the_training_size(tmp_path):
    from tests.neural.test_data import write_reconstruction

    write_reconstruction(tmp_path / "sfm")  # 80x60 photos, frame 0 held out
    runner = CliRunner()
    run = tmp_path / "run"
    result = runner.invoke(
        main,
        ["nerf", "train", str(tmp_path / "sfm"), "--out", str(run), "--steps", "1", "--batch-rays", "32",
         "--device", "cpu", "--bounded", "--background", "black", "--max-side", "40",
         "--no-depth-supervision", "--photo-appearance"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    config = json.loads((run / "config.json").read_text())
    assert (config["train"]["unbounded"], config["train"]["background"]) == (False, "black")
    assert config["train"]["depth_supervision"] is False and config["train"]["photo_appearance"] is True
    assert not config["scene"]["unbounded"] and config["train"]["max_side"] == 40
    assert len(list((run / "image_cache").glob("*.npy"))) == 5  # the resized photos, cached in the run

    result = runner.invoke(
        main,
        ["nerf", "eval", str(run), "--data", str(tmp_path / "sfm"), "--device", "cpu", "--save-renders",
         str(tmp_path / "heldout")],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads((run / "eval_val.json").read_text())
    assert [image["name"] for image in report["per_image"]] == ["1"]  # images/1.png: frame 0, held out
    assert Image.open(tmp_path / "heldout/1.png").size == (40, 30)
    result = runner.invoke(
        main,
        ["nerf", "render", str(run), "--poses", str(tmp_path / "sfm/transforms.json"), "--out",
         str(tmp_path / "renders"), "--device", "cpu"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert Image.open(tmp_path / "renders/1.png").size == (40, 30)  # not the file's 80x60
