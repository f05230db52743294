"""The CUDA path: training, evaluation and rendering on a GPU give what the CPU gives.

Runs only where torch sees a CUDA GPU (skipped elsewhere). The data is the analytic box scene written as a
tiny-NeRF file, so nothing beside the checkout is read.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neural import TrainConfig, evaluate, load_dataset, load_run, train
from neural.inference import render_frame, resolve_device, view_camera
from neural.rays import generate_rays
from tests.neural.box_scene import SCENE, look_at_pose, render_boxes

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA GPU (torch.cuda.is_available() is false)"
)

#: Ring cameras of the box scene: training views, held-out views (between them), pixels per side.
TRAIN_VIEWS, HELD_OUT_VIEWS, SIZE = 16, 4, 48
HALF_FOV_DEG = 25.0
#: Small grids so that a few hundred steps converge.
MODEL_OPTIONS = {"initial_voxels": 16**3, "final_voxels": 64**3, "upsample_steps": [40, 100]}
STEPS = 300
#: Held-out PSNR floor after STEPS (the same run on the CPU: 21.0 dB; an all-white image scores 10 dB).
HELD_OUT_PSNR_FLOOR_DB = 18.0


def ring_pose(angle: float, height: float) -> torch.Tensor:
    return look_at_pose(3.0 * torch.tensor([math.cos(angle), math.sin(angle), height]))


@pytest.fixture(scope="module")
def box_npz(tmp_path_factory) -> Path:
    """The box scene from TRAIN_VIEWS ring cameras (split 0) and HELD_OUT_VIEWS between them (split 1)."""
    focal = 0.5 * SIZE / math.tan(math.radians(HALF_FOV_DEG))
    poses, images = [], []
    views = [(2 * math.pi * k / TRAIN_VIEWS, 0.6 if k % 2 else -0.3) for k in range(TRAIN_VIEWS)]
    views += [(2 * math.pi * (k + 0.25) / HELD_OUT_VIEWS, 0.2) for k in range(HELD_OUT_VIEWS)]
    for angle, height in views:
        pose = ring_pose(angle, height)
        rays = generate_rays(pose, SIZE, SIZE, focal)
        images.append(render_boxes(rays.origins, rays.directions).reshape(SIZE, SIZE, 3))
        poses.append(pose)
    path = tmp_path_factory.mktemp("boxes") / "boxes.npz"
    np.savez(
        path,
        images=torch.stack(images).numpy().astype(np.float32),
        poses=torch.stack(poses).numpy().astype(np.float64),
        focal=np.float64(focal),
        split=np.array([0] * TRAIN_VIEWS + [1] * HELD_OUT_VIEWS),
        near=np.float64(SCENE.near),
        far=np.float64(SCENE.far),
    )
    return path


@pytest.fixture(scope="module")
def gpu_run(box_npz, tmp_path_factory) -> Path:
    """The fast model trained STEPS steps on the GPU, device left to "auto"."""
    run_dir = tmp_path_factory.mktemp("gpu_run") / "run"
    train(box_npz, run_dir, TrainConfig(model="fast", model_options=MODEL_OPTIONS, steps=STEPS, log_every=10,
                                        val_every=10**9))  # fmt: skip
    return run_dir


def test_auto_picks_the_gpu_and_the_run_records_it(gpu_run):
    assert resolve_device("auto").type == "cuda"
    assert load_run(gpu_run, device="auto").device.type == "cuda"
    stored = json.loads((gpu_run / "config.json").read_text())["train"]
    assert stored["device"] == "auto"


def test_training_on_the_gpu_lowers_the_loss_and_reaches_the_held_out_floor(gpu_run, box_npz):
    losses = [json.loads(line)["loss"] for line in (gpu_run / "metrics.jsonl").read_text().splitlines()
              if "loss" in json.loads(line)]  # fmt: skip
    assert len(losses) >= STEPS // 10 - 1
    assert all(math.isfinite(loss) for loss in losses)
    assert np.mean(losses[-5:]) < 0.2 * np.mean(losses[:3])
    metrics = evaluate(gpu_run, load_dataset(box_npz), split="val", device="cuda")
    assert len(metrics.per_image) == HELD_OUT_VIEWS
    assert metrics.mean_psnr >= HELD_OUT_PSNR_FLOOR_DB, metrics.mean_psnr


def test_a_checkpoint_trained_on_the_gpu_renders_the_same_image_on_the_cpu(gpu_run, box_npz):
    gpu, cpu = load_run(gpu_run, device="cuda"), load_run(gpu_run, device="cpu")
    assert next(gpu.model.parameters()).device.type == "cuda"
    assert next(cpu.model.parameters()).device.type == "cpu"
    dataset = load_dataset(box_npz)
    pose = dataset.normalization.pose_to_original(dataset.poses[dataset.split("val")[0]])
    camera = view_camera(gpu, SIZE, SIZE, None, None)
    on_gpu, on_cpu = render_frame(gpu, pose, camera), render_frame(cpu, pose, camera)
    rgb_gpu, rgb_cpu = on_gpu.rgb.cpu().numpy(), on_cpu.rgb.numpy()
    assert rgb_gpu.shape == rgb_cpu.shape == (SIZE, SIZE, 3)
    # Float sums in another order (and a sample kept or skipped at the occupancy threshold) differ slightly.
    assert np.mean(np.abs(rgb_gpu - rgb_cpu)) < 2e-3
    assert np.quantile(np.abs(rgb_gpu - rgb_cpu), 0.99) < 2e-2
    assert np.mean(np.abs(on_gpu.opacity.cpu().numpy() - on_cpu.opacity.numpy())) < 2e-3


def test_training_resumes_on_the_gpu_from_its_checkpoint(box_npz, tmp_path):
    run_dir = tmp_path / "run"
    first = train(box_npz, run_dir, TrainConfig(model="fast", model_options=MODEL_OPTIONS, steps=60,
                                                device="cuda", val_every=10**9))  # fmt: skip
    resumed = train(box_npz, run_dir, TrainConfig(steps=120, device="cuda"), resume=True)
    assert (first.step, resumed.step) == (60, 120)
    assert load_run(run_dir, device="cuda").step == 120


def test_a_render_on_the_gpu_of_an_empty_direction_is_background(gpu_run):
    """Rays that miss the scene box keep the background colour on the GPU (no stray samples)."""
    run = load_run(gpu_run, device="cuda")
    # Above the boxes, looking up: the camera's -z is the world's +z.
    away = np.array([[-1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 3.0], [0, 0, 0, 1.0]])
    rendered = render_frame(run, away, view_camera(run, 16, 16, None, None), frame="data")
    background = run.background.cpu().numpy()
    assert np.allclose(rendered.rgb.cpu().numpy(), background, atol=1e-2)
