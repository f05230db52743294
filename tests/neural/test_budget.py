"""Sizes chosen for the budget: the training photos' long side from the step rate, views within their
share of the training time, the expected time of a scene."""

import json
import math

import pytest

from neural.budget import (
    MIN_TRAIN_SIDE,
    MIN_VIDEO_FRAMES,
    MIN_VIEW_SIDE,
    PIXEL_PASSES,
    WATCHABLE_VIEW_SIDE,
    budget_steps,
    expected_seconds,
    plan_views,
    scaled_size,
    train_max_side,
    views_seconds,
)
from neural.config import TrainConfig
from neural.training import train
from tests.neural.conftest import TINY_VANILLA
from tests.neural.test_data import write_reconstruction


def test_the_training_side_lets_the_budget_draw_every_pixel_pixel_passes_times():
    side = train_max_side(steps=1000, batch_rays=4096, num_images=8, width=3072, height=2048)
    width, height = side, side * 2048 / 3072
    assert 8 * width * height * PIXEL_PASSES == pytest.approx(1000 * 4096, rel=0.01)
    assert side == 620


def test_the_training_side_stays_between_the_floor_and_the_photos_own_size():
    assert train_max_side(10**7, 4096, 8, 3072, 2048) == 3072
    assert train_max_side(10, 256, 8, 3072, 2048) == MIN_TRAIN_SIDE
    assert train_max_side(10, 256, 8, 120, 80) == 120  # small photos are never enlarged


def test_the_budget_in_steps_is_the_steps_or_the_minutes_at_the_measured_rate():
    assert budget_steps(500, None, 0.25) == 500
    assert budget_steps(None, 2.0, 0.25) == 480
    assert budget_steps(None, 2.0, None) is None


def test_views_that_fit_their_share_are_kept_as_asked():
    plan = plan_views(600.0, 1e-6, 800, 600, 36, 200, 2, 200, share=0.2)
    assert (plan.frames, plan.video_max_side, plan.held_out_max_side) == (36, 200, 200)
    assert plan.seconds == pytest.approx(1e-6 * (36 + 2) * 200 * 150)


def test_views_over_their_share_get_smaller_then_fewer_and_fit_it():
    rate = 2e-4  # seconds per ray: a slow CPU
    asked = views_seconds(rate, 800, 600, 36, 200, 2, 200)
    plan = plan_views(120.0, rate, 800, 600, 36, 200, 2, 200, share=0.2)
    assert asked > 24.0 and plan.seconds <= 24.0 + 1e-9
    assert plan.video_max_side < 200 and plan.frames >= MIN_VIDEO_FRAMES
    assert plan.seconds == pytest.approx(
        views_seconds(rate, 800, 600, plan.frames, plan.video_max_side, 2, plan.held_out_max_side)
    )


def test_views_lose_frames_before_they_shrink_below_a_watchable_size():
    rate = 1 / 1600  # seconds per ray of a 2-core CPU under load: 36 frames would fit at 90 px only
    plan = plan_views(600.0, rate, 3072, 2048, 36, 200, 1, 200, share=0.2)
    assert plan.video_max_side == WATCHABLE_VIEW_SIDE and MIN_VIDEO_FRAMES < plan.frames < 36
    assert plan.seconds <= 120.0
    slower = plan_views(600.0, 2 * rate, 3072, 2048, 36, 200, 1, 200, share=0.2)
    assert slower.frames == MIN_VIDEO_FRAMES and slower.video_max_side < WATCHABLE_VIEW_SIDE
    idle = plan_views(600.0, rate / 10, 3072, 2048, 36, 200, 1, 200, share=0.2)
    assert (idle.frames, idle.video_max_side) == (36, 200)


def test_views_are_never_cut_below_their_floors_nor_without_a_rate():
    plan = plan_views(1.0, 1e-2, 800, 600, 36, 200, 2, 200, share=0.2)
    assert (plan.frames, plan.video_max_side, plan.held_out_max_side) == (
        MIN_VIDEO_FRAMES, MIN_VIEW_SIDE, MIN_VIEW_SIDE,
    )  # fmt: skip
    small = plan_views(1.0, 1e-2, 800, 600, 2, 40, 2, 32, share=0.2)
    assert (small.frames, small.video_max_side, small.held_out_max_side) == (2, 40, 32)  # never raised
    unknown = plan_views(1.0, None, 800, 600, 36, 200, 2, 200)
    assert (unknown.frames, unknown.video_max_side) == (36, 200) and math.isnan(unknown.seconds)


def test_scaled_sizes_keep_the_aspect_with_even_sides():
    assert scaled_size(3072, 2048, 200) == (200, 134)
    assert scaled_size(100, 50, 200) == (100, 50)


def test_a_scene_is_expected_to_take_reconstruction_training_and_at_most_a_fifth_more_for_views():
    expected = expected_seconds(10.0, 8, 0.2)
    assert expected["training"] == 600.0 and expected["views"] == 120.0
    assert expected["total"] == pytest.approx(sum(v for k, v in expected.items() if k != "total"))
    assert expected_seconds(None, 8, 0.2) is None


def test_photos_without_a_size_train_at_the_budgets_size_recorded_in_config_json(tmp_path):
    write_reconstruction(tmp_path / "sfm")  # 80 x 60 photos: any budget trains them whole
    config = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=2, batch_rays=16, device="cpu")
    train(tmp_path / "sfm", tmp_path / "run", config)
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())
    size = recorded["train_size"]
    assert size["max_side"] == recorded["train"]["max_side"] == 80 and size["full_side"] == 80
    assert size["budget_steps"] == 2 and size["seconds_per_step"] > 0 and size["render_seconds_per_ray"] > 0
    config = config.model_copy(update={"max_side": 40})
    train(tmp_path / "sfm", tmp_path / "given", config)
    given = json.loads((tmp_path / "given" / "config.json").read_text())
    assert "train_size" not in given and given["camera"]["width"] == 40
