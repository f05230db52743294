"""Training: losses, logs, checkpoints kept, resume identical to an uninterrupted run, stop conditions."""

import json

import numpy as np
import pytest
import torch

from neural.checkpoints import list_checkpoints, load_checkpoint
from neural.config import TrainConfig
from neural.data import load_dataset
from neural.errors import CheckpointError
from neural.training import RayBatchSampler, learning_rate_factor, train
from tests.neural.conftest import TINY_VANILLA


def tiny_config(**changes) -> TrainConfig:
    settings = dict(
        model="vanilla", model_options=TINY_VANILLA, steps=4, batch_rays=32, log_every=1, checkpoint_every=2,
        val_every=100, device="cpu", seed=3,
    )  # fmt: skip
    settings.update(changes)
    return TrainConfig(**settings)


def read_metrics(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines]


@pytest.mark.parametrize("photo_appearance", [False, True], ids=["field", "field+appearance"])
def test_resume_gives_the_same_next_losses_as_an_uninterrupted_run(tiny_npz, tmp_path, photo_appearance):
    train(tiny_npz, tmp_path / "whole", tiny_config(steps=4, photo_appearance=photo_appearance))
    train(tiny_npz, tmp_path / "split", tiny_config(steps=2, photo_appearance=photo_appearance))
    resumed = train(tiny_npz, tmp_path / "split", TrainConfig(steps=4), resume=True)
    assert resumed.step == 4
    whole = {m["step"]: m["loss"] for m in read_metrics(tmp_path / "whole") if "loss" in m}
    split = {m["step"]: m["loss"] for m in read_metrics(tmp_path / "split") if "loss" in m}
    assert sorted(split) == [1, 2, 3, 4]
    assert split == whole  # bit-identical, steps 3 and 4 included
    assert len(set(whole.values())) == 4  # the losses do move (the test can fail)


def test_run_folder_has_config_metrics_val_png_and_latest_and_best_checkpoints(tiny_npz, tmp_path):
    run = tmp_path / "run"
    result = train(tiny_npz, run, tiny_config(steps=6, val_every=2))
    config = json.loads((run / "config.json").read_text())
    assert config["train"]["model"] == "vanilla" and config["train"]["lr"] == 5e-4  # the model's default
    records = read_metrics(run)
    assert {"step", "loss", "psnr", "lr", "seconds"} <= set(records[0])
    val = [r for r in records if "val_psnr" in r]
    assert [r["step"] for r in val] == [2, 4, 6]
    assert sorted(p.name for p in (run / "val").iterdir()) == [f"step_000000{s}.png" for s in (2, 4, 6)]
    checkpoints = list_checkpoints(run)
    best_step = max(val, key=lambda r: r["val_psnr"])["step"]
    assert [c.step for c in checkpoints] == sorted({best_step, 6})
    assert [c.step for c in checkpoints if c.is_latest] == [6] and [
        c.step for c in checkpoints if c.is_best
    ] == [best_step]
    assert sorted(p.name for p in (run / "checkpoints").glob("*.pt")) == sorted(
        c.path.name for c in checkpoints
    )
    payload = load_checkpoint(result.latest_checkpoint)
    assert {"model_state", "optimizer_state", "rng", "train_config", "step"} <= set(payload)
    assert payload["step"] == 6 and set(payload["rng"]) >= {"torch", "numpy", "python", "generator"}


def test_learning_rate_decays_exponentially():
    config = TrainConfig(lr=1e-3, lr_decay=0.1, lr_decay_steps=1000)
    assert learning_rate_factor(0, config) == 1.0
    assert learning_rate_factor(500, config) == pytest.approx(0.1**0.5)
    assert learning_rate_factor(2000, config) == pytest.approx(0.01)


def test_minutes_and_stop_callback_end_training(tiny_npz, tmp_path):
    timed = train(tiny_npz, tmp_path / "timed", tiny_config(steps=None, minutes=1e-6))
    assert timed.stopped_by == "minutes" and timed.step == 1
    asked = []

    def stop_on_third_question() -> bool:
        asked.append(1)
        return len(asked) >= 3

    stopped = train(tiny_npz, tmp_path / "stopped", tiny_config(steps=50), should_stop=stop_on_third_question)
    # asked before the first step and after each step: the third answer comes after step 2
    assert stopped.stopped_by == "stop_requested" and stopped.step == 2
    assert list_checkpoints(tmp_path / "stopped")[-1].step == 2


def test_precrop_samples_only_the_central_pixels(tiny_npz):
    dataset = load_dataset(tiny_npz)
    sampler = RayBatchSampler(dataset, dataset.split("train"), torch.device("cpu"))
    generator = torch.Generator().manual_seed(0)
    centre = torch.as_tensor(dataset.images[dataset.split("train")][:, 5:15, 5:15].reshape(-1, 3))

    def distance_to_centre_colours(colours):
        return torch.cdist(colours, centre, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values

    _, _, cropped, _ = sampler.sample(4000, generator, crop_fraction=0.5)
    assert distance_to_centre_colours(cropped).max() == 0  # every colour is a centre pixel's
    _, _, anywhere, _ = sampler.sample(4000, generator)
    assert distance_to_centre_colours(anywhere).max() > 0.01


def test_progress_and_metrics_callbacks_are_called(tiny_npz, tmp_path):
    fractions, records = [], []
    config = tiny_config(steps=2)
    train(
        tiny_npz,
        tmp_path / "r",
        config,
        progress=lambda *event: fractions.append(event),
        metrics_callback=records.append,
    )
    assert fractions == [("train", 0.5), ("train", 1.0)]
    assert [r["step"] for r in records if "loss" in r] == [1, 2]


def test_bad_runs_are_refused(tiny_npz, tmp_path, shared_data):
    run = tmp_path / "run"
    train(tiny_npz, run, tiny_config(steps=2))
    with pytest.raises(CheckpointError, match="already holds a training run"):
        train(tiny_npz, run, tiny_config(steps=2))
    with pytest.raises(CheckpointError, match="cannot resume it as 'fast'"):
        train(tiny_npz, run, TrainConfig(model="fast", steps=3), resume=True)
    with pytest.raises(CheckpointError, match="not a training run"):
        train(tiny_npz, tmp_path / "empty", TrainConfig(steps=3), resume=True)
    with pytest.raises(CheckpointError, match="resume with the data it was trained on"):
        train(shared_data / "lego_tiny.npz", run, TrainConfig(steps=3), resume=True)
    latest = list_checkpoints(run)[-1].path
    payload = torch.load(latest, weights_only=False)
    payload["format_version"] = 999
    torch.save(payload, latest)
    with pytest.raises(CheckpointError, match="format version 999 is incompatible"):
        train(tiny_npz, run, TrainConfig(steps=3), resume=True)
    latest.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        train(tiny_npz, run, TrainConfig(steps=3), resume=True)


def test_checkpoint_of_another_architecture_is_refused(tiny_npz, tmp_path):
    from neural.inference import load_run

    run = tmp_path / "run"
    train(tiny_npz, run, tiny_config(steps=2))
    config = json.loads((run / "config.json").read_text())
    latest = list_checkpoints(run)[-1].path
    payload = torch.load(latest, weights_only=False)
    payload["model_name"] = "fast"
    torch.save(payload, latest)
    with pytest.raises(CheckpointError, match="holds model 'fast'"):
        load_run(run)
    payload["model_name"] = "vanilla"
    payload["model_state"] = {k: v for k, v in payload["model_state"].items() if not k.startswith("fine.")}
    torch.save(payload, latest)
    with pytest.raises(CheckpointError, match="does not fit this model"):
        load_run(run)
    assert config["train"]["model"] == "vanilla"


def test_resume_after_the_fast_model_resized_its_grids_matches_an_uninterrupted_run(tiny_npz, tmp_path):
    grids = dict(initial_voxels=12**3, final_voxels=16**3, upsample_steps=[2], occupancy_warmup_steps=1,
                 occupancy_update_every=1)  # fmt: skip
    config = dict(model="fast", model_options=grids, batch_rays=64, log_every=1, val_every=100, device="cpu")
    train(tiny_npz, tmp_path / "whole", TrainConfig(steps=5, checkpoint_every=100, **config))
    train(tiny_npz, tmp_path / "split", TrainConfig(steps=3, checkpoint_every=100, **config))
    train(tiny_npz, tmp_path / "split", TrainConfig(steps=5), resume=True)
    whole = [m["loss"] for m in read_metrics(tmp_path / "whole") if "loss" in m]
    split = [m["loss"] for m in read_metrics(tmp_path / "split") if "loss" in m]
    assert split == whole and len(whole) == 5


def test_a_run_resumes_as_the_model_it_saved_when_the_model_defaults_changed_since(tiny_npz, tmp_path):
    """The checkpoint's complete model config, not today's defaults, rebuilds the model: a run trained when
    the fast model's colour was diffuse (sh_degree 0, its options unset in config.json) resumes as that."""
    grids = dict(initial_voxels=12**3, final_voxels=16**3, upsample_steps=[2], sh_degree=0)
    run = tmp_path / "run"
    train(tiny_npz, run, TrainConfig(model="fast", model_options=grids, steps=3, batch_rays=64, device="cpu"))
    config = json.loads((run / "config.json").read_text())
    config["train"]["model_options"] = {}  # as written by a version whose defaults were these options
    (run / "config.json").write_text(json.dumps(config))
    resumed = train(tiny_npz, run, TrainConfig(steps=5), resume=True)
    assert resumed.step == 5
    assert load_checkpoint(resumed.latest_checkpoint)["model_config"]["sh_degree"] == 0


def test_validation_downscale_keeps_pixel_blocks_and_their_rays_aligned():
    from neural.inference import PinholeIntrinsics
    from neural.rays import generate_rays, pixel_rays
    from neural.training import downscale

    image = np.arange(4 * 6 * 3, dtype=np.float64).reshape(4, 6, 3)
    small = downscale(image, 2)
    assert small.shape == (2, 3, 3)
    np.testing.assert_allclose(small[1, 2], image[2:4, 4:6].mean(axis=(0, 1)))
    camera = PinholeIntrinsics(6, 4, fx=5.0, fy=5.0, cx=3.2, cy=1.9)
    half = camera.downscaled(2)
    c2w = torch.eye(4, dtype=torch.float64)
    small_rays = generate_rays(c2w, half.width, half.height, half.fx, half.fy, half.cx, half.cy)
    # small pixel (u, v) covers original pixels 2u..2u+1: its centre is the original point (2u + 1, 2v + 1)
    u, v = torch.tensor([0.5, 4.5], dtype=torch.float64), torch.tensor([0.5, 2.5], dtype=torch.float64)
    expected = pixel_rays(c2w, u, v, camera.fx, camera.fy, camera.cx, camera.cy)
    torch.testing.assert_close(small_rays.directions[[0, 5]], expected.directions)


def test_a_reader_racing_the_trainer_gets_the_new_latest_checkpoint(tmp_path, monkeypatch):
    from neural import checkpoints

    checkpoints.save_checkpoint(tmp_path, {"weights": 1}, step=1, val_psnr=None)
    real_load = checkpoints.load_checkpoint
    raced = []

    def load_while_the_trainer_saves(path, map_location="cpu"):
        if not raced:  # between the reader's resolve and load, step 2 is saved and step 1 pruned
            raced.append(path.name)
            checkpoints.save_checkpoint(tmp_path, {"weights": 2}, step=2, val_psnr=None)
        return real_load(path, map_location=map_location)

    monkeypatch.setattr(checkpoints, "load_checkpoint", load_while_the_trainer_saves)
    path, payload = checkpoints.load_named_checkpoint(tmp_path, "latest")
    assert raced == ["step_0000001.pt"]
    assert path.name == "step_0000002.pt" and payload["weights"] == 2


def test_a_corrupt_checkpoint_is_still_an_error_when_nothing_moved(tmp_path):
    from neural import checkpoints

    saved = checkpoints.save_checkpoint(tmp_path, {"weights": 1}, step=1, val_psnr=None)
    saved.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        checkpoints.load_named_checkpoint(tmp_path, "latest")


# ------------------------------------------------------------------------------------------- held-out views
@pytest.mark.parametrize("data_kind", ["npz", "reconstruction"])
def test_held_out_views_never_reach_a_training_batch(data_kind, tiny_npz, tmp_path, monkeypatch):
    from tests.neural.test_data import write_reconstruction

    if data_kind == "npz":
        data = tiny_npz
    else:
        data = tmp_path / "sfm"
        write_reconstruction(data)
    dataset = load_dataset(data)
    train_views, held_out = set(dataset.split("train")), set(dataset.split("val"))
    assert held_out and not train_views & held_out
    batches = []
    real_sample = RayBatchSampler.sample

    def recording_sample(self, *args, **kwargs):
        batch = real_sample(self, *args, **kwargs)
        batches.append(batch)
        return batch

    monkeypatch.setattr(RayBatchSampler, "sample", recording_sample)
    grids = dict(initial_voxels=8**3, final_voxels=8**3, upsample_steps=[1000])
    # a given size: no budget probe, whose batches (of training views too) would count here
    train(data, tmp_path / "run", TrainConfig(model="fast", model_options=grids, steps=3, batch_rays=2000,
                                              device="cpu", val_every=1, max_side=80))  # fmt: skip
    assert len(batches) == 3 + (data_kind == "reconstruction")  # photos: one draw fits their environment
    origins = torch.cat([batch[0] for batch in batches]).double()
    colours = torch.cat([batch[2] for batch in batches])
    centres = torch.as_tensor(dataset.poses[:, :3, 3]).double()
    camera_of_ray = torch.cdist(origins, centres).argmin(dim=1)
    assert set(camera_of_ray.tolist()) == train_views  # every training view, and no held-out one
    # and every target colour is a training image's pixel
    train_pixels = torch.as_tensor(dataset.images[sorted(train_views)].reshape(-1, 3))
    nearest = torch.cdist(colours, train_pixels, compute_mode="donot_use_mm_for_euclid_dist").min(1).values
    assert nearest.max() == 0


def test_a_reconstruction_trains_unbounded_on_random_backgrounds_by_default_and_records_it(tmp_path):
    from tests.neural.test_data import write_reconstruction

    write_reconstruction(tmp_path / "sfm")
    grids = dict(initial_voxels=8**3, final_voxels=8**3, upsample_steps=[1000])
    config = TrainConfig(model="fast", model_options=grids, steps=1, batch_rays=64, device="cpu", max_side=40)
    train(tmp_path / "sfm", tmp_path / "run", config)
    config = json.loads((tmp_path / "run/config.json").read_text())
    assert config["train"]["background"] == "random" and config["train"]["unbounded"] is True
    assert config["scene"]["unbounded"] is True and config["train"]["max_side"] == 40
    assert (config["camera"]["width"], config["camera"]["height"]) == (40, 30)
    # the vanilla model renders bounded scenes only: the default follows it, asking for more is an error
    vanilla = TrainConfig(model="vanilla", model_options=TINY_VANILLA, steps=1, batch_rays=16, device="cpu")
    train(tmp_path / "sfm", tmp_path / "vanilla", vanilla)
    assert json.loads((tmp_path / "vanilla/config.json").read_text())["scene"]["unbounded"] is False
    with pytest.raises(ValueError, match="does not support unbounded scenes"):
        train(tmp_path / "sfm", tmp_path / "bad", vanilla.model_copy(update={"unbounded": True}))


def test_synthetic_data_keeps_the_white_bounded_world_and_old_run_configs_still_load(tiny_npz, tmp_path):
    train(tiny_npz, tmp_path / "run", tiny_config(steps=1))
    config = json.loads((tmp_path / "run/config.json").read_text())
    assert config["train"]["background"] == "white" and config["train"]["unbounded"] is False
    legacy = {k: v for k, v in config["train"].items() if k not in ("background", "unbounded")}
    assert TrainConfig.model_validate({**legacy, "white_background": False}).background == "black"


def test_a_reconstruction_trains_the_depth_loss_and_without_enough_points_says_why(tmp_path, caplog):
    from tests.neural.test_data import write_depths_of, write_reconstruction

    _, poses, points = write_reconstruction(tmp_path / "sfm")
    write_depths_of(tmp_path / "sfm", poses, points)
    grids = dict(initial_voxels=8**3, final_voxels=8**3, upsample_steps=[1000])
    config = TrainConfig(model="fast", model_options=grids, steps=2, batch_rays=64, depth_rays=32,
                         device="cpu", max_side=40, log_every=1)  # fmt: skip
    train(tmp_path / "sfm", tmp_path / "run", config)
    stored = json.loads((tmp_path / "run/config.json").read_text())
    assert stored["train"]["depth_supervision"] is True
    # the photos' total variation under the user's own model options
    assert stored["train"]["model_options"] == {**grids, "tv_density_weight": 1e-4, "tv_color_weight": 1e-3}
    depth = stored["depth_supervision"]
    assert depth["used"] is True and depth["rays"] > 100 and depth["uncertainty"] == "covariance"
    assert depth["median_sigma"] == pytest.approx(0.05 * stored["normalization"]["scale"])
    assert all(np.isfinite(record["loss"]) for record in read_metrics(tmp_path / "run") if "loss" in record)

    write_depths_of(tmp_path / "sfm", poses, points[:10])  # 50 observations
    with caplog.at_level("WARNING", logger="neural.training"):
        train(tmp_path / "sfm", tmp_path / "few", config)
    depth = json.loads((tmp_path / "few/config.json").read_text())["depth_supervision"]
    assert depth["used"] is False and depth["reason"].startswith("too few sparse points")
    assert "training without depth supervision: too few sparse points" in caplog.text


def test_each_depth_rays_sigma_is_its_points_own_or_the_median_raised_to_the_floor(tmp_path):
    from neural.training import DepthRaySampler
    from tests.neural.test_data import write_depths_of, write_reconstruction

    _, poses, points = write_reconstruction(tmp_path)
    write_depths_of(tmp_path, poses, points)
    dataset = load_dataset(tmp_path)
    train_views = dataset.split("train")
    own = dataset.depth_rays.of_images(train_views).sigma.copy()
    own[::2] *= 3.0  # the points' own std-devs differ, so the constant median is not every ray's own
    dataset.depth_rays.sigma[np.isin(dataset.depth_rays.image, train_views)] = own
    for uncertainty, expected in (("covariance", own), ("constant", np.full_like(own, np.median(own)))):
        for floor in (0.04, 1e-6):
            config = TrainConfig(depth_uncertainty=uncertainty, depth_min_sigma=floor)
            sampler = DepthRaySampler(dataset, train_views, config, torch.device("cpu"))
            np.testing.assert_allclose(sampler.sigma.numpy(), np.sqrt(expected**2 + floor**2))
    with pytest.raises(ValueError, match="depth_min_sigma"):
        TrainConfig(depth_min_sigma=0)


def test_synthetic_data_trains_without_depth_supervision_by_default(tiny_npz, tmp_path):
    train(tiny_npz, tmp_path / "run", tiny_config(steps=1))
    stored = json.loads((tmp_path / "run/config.json").read_text())
    assert stored["train"]["depth_supervision"] is False
    assert "tv_density_weight" not in stored["train"]["model_options"]
    assert stored["depth_supervision"] == {"used": False, "reason": "off"}


def test_random_states_of_a_gpu_run_restore_on_a_cpu_generator():
    """A CUDA generator's state (16 bytes: seed and offset) cannot be set on a CPU generator; a GPU run
    resumed on a CPU seeds its ray draws from it instead, the same way each time."""
    from neural.training import restore_rng_states, rng_states

    states = rng_states(torch.Generator().manual_seed(3))
    states["generator"] = torch.tensor(list(range(16)), dtype=torch.uint8)  # as torch.cuda's generator saves
    draws = []
    for _ in range(2):
        generator = torch.Generator()
        restore_rng_states(states, generator)
        draws.append(torch.rand(4, generator=generator))
    assert torch.equal(draws[0], draws[1])
    assert not torch.equal(draws[0], torch.rand(4, generator=torch.Generator().manual_seed(3)))
