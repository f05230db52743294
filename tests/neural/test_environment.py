"""The environment of a photographed scene: the photos' colours by direction, fitted by least squares and
shown where a render's field is empty."""

import json

import numpy as np
import pytest
import torch

from neural.config import TrainConfig
from neural.environment import Environment, background_for, direction_basis, fit_environment
from neural.inference import load_run, render_image
from neural.rays import generate_rays
from neural.training import train
from tests.neural.test_data import write_reconstruction

SMALL_GRIDS = {"initial_voxels": 12**3, "final_voxels": 16**3}
SKY_ABOVE = np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.3, 0.3, 0.4]])
"""Grey at the horizon, brighter and bluer upwards (+z)."""


def random_directions(count: int, seed: int = 0) -> torch.Tensor:
    return torch.as_tensor(np.random.default_rng(seed).normal(size=(count, 3)))


def test_the_fit_recovers_a_colour_gradient_over_the_sphere():
    directions = random_directions(5000) * 3.0  # any length: only the direction counts
    colours = direction_basis(directions) @ torch.as_tensor(SKY_ABOVE)
    fitted = fit_environment(directions, colours)
    np.testing.assert_allclose(fitted.coefficients, SKY_ABOVE, atol=1e-9)
    up, down = fitted.colours(torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(up.numpy(), [0.8, 0.8, 0.9], atol=1e-9)
    np.testing.assert_allclose(down.numpy(), [0.2, 0.2, 0.1], atol=1e-9)


def test_colours_stay_between_black_and_white():
    glaring = Environment(np.array([[0.5] * 3, [2.0] * 3, [0.0] * 3, [0.0] * 3]))
    colours = glaring.colours(random_directions(1000))
    assert colours.min() == 0.0 and colours.max() == 1.0


def test_a_constant_background_is_kept_and_an_environment_gives_each_ray_its_colour():
    directions = random_directions(7)
    white = torch.ones(3)
    assert background_for(white, directions) is white
    assert background_for(Environment(SKY_ABOVE), directions).shape == (7, 3)


@pytest.mark.parametrize("values", [[[0.0] * 3] * 3, [[0.0] * 3] * 3 + [[float("nan")] * 3]])
def test_stored_coefficients_of_the_wrong_shape_or_not_finite_are_refused(values):
    with pytest.raises(ValueError, match="4x3 finite"):
        Environment.from_list(values)


def test_a_photo_run_renders_its_empty_directions_in_the_photos_colours_not_black(tmp_path):
    write_reconstruction(tmp_path / "sfm")  # flat grey photos, 40 * index grey levels
    config = TrainConfig(model="fast", model_options=SMALL_GRIDS, steps=2, batch_rays=64, device="cpu")
    train(tmp_path / "sfm", tmp_path / "run", config)
    run = load_run(tmp_path / "run", device="cpu")
    assert json.loads((tmp_path / "run" / "config.json").read_text())["train"]["background"] == "random"
    assert isinstance(run.background, Environment)
    photos_mean = np.mean([40 * index for index in (1, 2, 3, 4)]) / 255  # the training photos (not 0)
    assert run.background.coefficients[0].mean() == pytest.approx(photos_mean, abs=0.1)

    pose = torch.as_tensor(run.default_pose(), dtype=torch.float32)
    shown = render_image(run.model, pose, run.camera, run.scene, run.background, 1024)
    on_black = render_image(run.model, pose, run.camera, run.scene, torch.zeros(3), 1024)
    rays = generate_rays(pose, run.camera.width, run.camera.height, run.camera.fx, run.camera.fy,
                         run.camera.cx, run.camera.cy)
    seen_through = (1.0 - on_black.opacity).reshape(-1, 1)
    assert float(seen_through.mean()) > 0.05  # a field of 2 steps is thin: the environment shows through
    expected = on_black.rgb.reshape(-1, 3) + seen_through * run.background.colours(rays.directions)
    np.testing.assert_allclose(shown.rgb.reshape(-1, 3).numpy(), expected.numpy(), atol=1e-5)

    config = config.model_copy(update={"render_environment": False})
    train(tmp_path / "sfm", tmp_path / "black", config)
    black = load_run(tmp_path / "black", device="cpu")
    assert isinstance(black.background, torch.Tensor) and float(black.background.max()) == 0.0
