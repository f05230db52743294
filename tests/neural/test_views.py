"""Views where the photos were: a run records its registered cameras; a render without a camera is the
default photo's view; requests on photo scenes are read relative to the capture; a view of nothing says so."""

import json

import numpy as np
import pytest
import torch

from neural.camera_path import CAPTURE_FRAME_EYE, CameraPathError
from neural.config import TrainConfig
from neural.inference import (
    EmptyViewError,
    PinholeIntrinsics,
    RenderedImage,
    camera_path,
    check_sees_scene,
    load_run,
    look_at,
    render_image,
    render_view,
)
from neural.training import train
from tests.neural.conftest import TINY_VANILLA
from tests.neural.test_data import write_reconstruction


@pytest.fixture(scope="module")
def photo_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("photos")
    write_reconstruction(folder / "sfm")
    config = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=1, batch_rays=16, device="cpu")
    train(folder / "sfm", folder / "run", config)
    return folder


def test_a_photo_run_records_every_registered_camera_in_its_config(photo_run):
    run = load_run(photo_run / "run")
    assert run.photos and run.cameras.shape == (5, 4, 4)  # held-out photos included
    transforms = json.loads((photo_run / "sfm" / "transforms.json").read_text())
    for frame, c2w_scene in zip(transforms["frames"], run.cameras, strict=True):
        original = run.normalization.pose_to_original(c2w_scene)
        np.testing.assert_allclose(original, frame["transform_matrix"], atol=1e-5)


def test_a_render_without_a_camera_is_the_default_photos_view(photo_run):
    run = load_run(photo_run / "run")
    default = run.cameras[run.capture().default_index]
    camera = PinholeIntrinsics(16, 12, 20.0, 20.0, 8.0, 6.0)
    expected = render_image(run.model, torch.as_tensor(default, dtype=torch.float32), camera, run.scene,
                            run.background, 64)  # fmt: skip
    rendered = render_view(photo_run / "run", None, 16, 12, fx=20.0).astype(int)
    assert np.abs(rendered - (expected.rgb.numpy() * 255 + 0.5).astype(int)).max() <= 1


def test_the_camera_path_is_in_the_datasets_frame_and_its_default_view_is_a_photo(photo_run):
    path = camera_path(photo_run / "run", 7)
    transforms = json.loads((photo_run / "sfm" / "transforms.json").read_text())
    photos = np.array([frame["transform_matrix"] for frame in transforms["frames"]])
    assert np.abs(photos - np.asarray(path["default_view"])).max(axis=(1, 2)).min() < 1e-5
    assert len(path["path"]) == 7 and len(path["cameras"]) == 5
    assert path["kind"] in ("ring", "arc", "walk")


def test_a_blender_style_request_on_a_photo_scene_is_read_relative_to_the_capture(photo_run):
    """eye (0, -4, 1) looking at the origin with z up is the default photo's camera."""
    run = load_run(photo_run / "run")
    default = run.cameras[run.capture().default_index]
    request = look_at(np.array(CAPTURE_FRAME_EYE), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    pose = run.pose_to_scene(request, "auto")
    np.testing.assert_allclose(pose[:3, 3], default[:3, 3], atol=1e-6)
    np.testing.assert_allclose(pose[:3, 2], default[:3, 2], atol=1e-6)  # the same optical axis
    # the data frame (free mode) is the dataset's own
    np.testing.assert_allclose(run.pose_to_scene(request, "data"), run.normalization.pose_to_scene(request))


def test_requests_on_blender_and_npz_data_stay_in_the_datas_frame(tiny_npz, tmp_path):
    config = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=1, batch_rays=16, device="cpu")
    train(tiny_npz, tmp_path / "run", config)
    run = load_run(tmp_path / "run")
    assert not run.photos and len(run.cameras) == len(np.load(tiny_npz)["poses"])
    request = look_at(np.array([0.0, -4.0, 1.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(run.pose_to_scene(request, "auto"), request)


def test_a_view_of_an_empty_field_is_refused_saying_it_sees_nothing(tiny_npz, tmp_path):
    config = TrainConfig(
        model="fast", model_options={"initial_voxels": 16**3, "final_voxels": 16**3, "initial_alpha": 1e-9},
        steps=1, batch_rays=16, device="cpu", lr=1e-12,
    )  # fmt: skip
    train(tiny_npz, tmp_path / "run", config)
    with pytest.raises(EmptyViewError, match="sees nothing of the scene"):
        render_view(tmp_path / "run", None, 16, 12)


def test_a_view_that_partly_sees_the_scene_is_kept_and_a_transparent_or_hazy_one_is_not():
    sliver = torch.zeros(20, 20)
    sliver[:, :1] = 0.9  # 5 % of the pixels see the scene
    assert (
        check_sees_scene(RenderedImage(torch.zeros(20, 20, 3), torch.ones(20, 20), sliver)).opacity is sliver
    )
    for opacity in (torch.zeros(20, 20), torch.full((20, 20), 0.06)):  # nothing; a haze (Herz-Jesus-P8)
        with pytest.raises(EmptyViewError, match="sees nothing"):
            check_sees_scene(RenderedImage(torch.zeros(20, 20, 3), torch.ones(20, 20), opacity))


def test_a_run_without_registered_cameras_has_no_camera_path(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"cameras": {"c2w": []}, "normalization": {}}))
    with pytest.raises(CameraPathError, match="no registered cameras"):
        camera_path(tmp_path, 10)


def test_the_render_command_writes_the_default_view_and_a_video_along_the_cameras(photo_run, tmp_path):
    from click.testing import CliRunner
    from PIL import Image

    from service.cli import main

    runner = CliRunner()
    result = runner.invoke(main, ["nerf", "render", str(photo_run / "run"), "--view", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert Image.open(tmp_path / "view.png").size == (80, 60)
    command = ["nerf", "render", str(photo_run / "run"), "--orbit", "4", "--width", "16", "--height", "12"]
    result = runner.invoke(main, [*command, "--out", str(tmp_path / "video")])
    assert result.exit_code == 0, result.output
    assert Image.open(tmp_path / "video" / "orbit.gif").n_frames == 4


def test_the_scene_command_takes_render_max_side_and_warns_that_max_side_is_deprecated(tmp_path):
    from click.testing import CliRunner

    from service.cli import main

    (tmp_path / "photos").mkdir()
    command = ["scene", str(tmp_path / "photos"), "--out", str(tmp_path / "out"), "--minutes", "1"]
    result = CliRunner().invoke(main, [*command, "--max-side", "64"])
    assert "--max-side is deprecated; it is --render-max-side" in result.output
    assert "expected: reconstruction 0 s, training 60 s, views 12 s, total 72 s" in result.output
    result = CliRunner().invoke(main, [*command, "--render-max-side", "64", "--train-max-side", "4"])
    assert result.exit_code == 1 and "max_side" in result.output and "deprecated" not in result.output
