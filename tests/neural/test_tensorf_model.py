"""The factorized (TensoRF VM) model, the occupancy grid as a density estimator shared by every model, and the
distortion loss."""

from __future__ import annotations

import json

import pytest
import torch

from neural.config import TrainConfig
from neural.inference import load_run
from neural.models import build_model
from neural.models.fast import FastModel, FastModelConfig
from neural.models.tensorf import TensorVMConfig, TensorVMModel
from neural.occupancy import OccupancyGrid
from neural.rendering import packed_distortion
from neural.training import train
from tests.neural.box_scene import SCENE, WHITE, fit, psnr, ring_views

SMALL = dict(
    initial_voxels=16**3,
    final_voxels=48**3,
    upsample_steps=[30, 60],
    occupancy_warmup_steps=20,
    occupancy_update_every=8,
)


def render_all(model, origins, directions) -> torch.Tensor:
    with torch.no_grad():
        return model.render_rays(origins, directions, SCENE.near, SCENE.far, WHITE, train=False).rgb


# ----------------------------------------------------------------------------------------------- the model
def test_vm_model_fits_the_box_scene_above_35_db_and_learns_where_it_is_empty():
    torch.manual_seed(0)
    origins, directions, colours = ring_views(num_views=6, size=24)
    model = build_model("tensorf", SCENE, **SMALL, density_components=4, color_components=8)
    fit(model, origins, directions, colours, steps=100, batch=512, lr=0.1)

    assert psnr(render_all(model, origins, directions), colours) > 35.0
    assert model.occupancy.occupied_fraction() < 0.6
    face_centres = torch.tensor([[-0.35, -0.5, -0.15], [0.6, 0.0, 0.0], [0.0, -0.35, 0.6]])
    assert model.occupancy.query(face_centres).all()


def test_vm_factors_are_planes_and_lines_and_cost_far_less_than_a_dense_lattice():
    model = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=40**3, density_components=4))
    x, y, z = model.lattice_shape
    assert [tuple(f.shape) for f in model.density] == [
        (1, 4, x, y), (1, 4, x, z), (1, 4, y, z), (1, 4, z, 1), (1, 4, y, 1), (1, 4, x, 1),
    ]  # fmt: skip
    assert sum(f.numel() for f in model.density) < 0.3 * x * y * z


def test_the_vm_field_is_the_sum_of_plane_times_line_products_at_points_and_lattice_vertices():
    model = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=8**3, density_components=2))
    point = torch.tensor([[0.2, -0.4, 0.7]])
    u = (point - model.box_min) / (model.box_max - model.box_min) * 2 - 1  # in [-1, 1]
    (x, y, z), expected = model.lattice_shape, 0.0
    index = ((u[0] + 1) / 2 * (torch.tensor([x, y, z]) - 1)).tolist()

    def interp(tensor: torch.Tensor, coords: list[float]) -> torch.Tensor:
        """Multilinear interpolation of tensor (R, n_1, ..., n_k) at fractional indices, by hand."""
        if not coords:
            return tensor
        low = int(coords[0])
        frac = coords[0] - low
        high = min(low + 1, tensor.shape[1] - 1)
        return (1 - frac) * interp(tensor[:, low], coords[1:]) + frac * interp(tensor[:, high], coords[1:])

    for mode, (a, b, c) in enumerate(((0, 1, 2), (0, 2, 1), (1, 2, 0))):
        plane = interp(model.density[mode][0].detach(), [index[a], index[b]])
        line = interp(model.density[3 + mode][0, :, :, 0].detach(), [index[c]])
        expected = expected + (plane * line).sum()
    with torch.no_grad():
        raw = torch.log(model.density_at(point)) - model.density_shift
    assert float(raw) == pytest.approx(float(expected), abs=1e-5)
    with torch.no_grad():
        vertices = torch.tensor([[0, 0, 0], [x - 1, 2, 5], [3, y - 1, z - 1]])
        world = model.box_min + vertices / (torch.tensor([x, y, z]) - 1) * (model.box_max - model.box_min)
        assert torch.allclose(model.lattice_density()[tuple(vertices.T)], model.density_at(world), rtol=1e-4)


def test_upsampling_refits_the_factors_to_the_occupied_box():
    model = TensorVMModel(SCENE, TensorVMConfig(**{**SMALL, "upsample_steps": [5]}))
    with torch.no_grad():
        for factor in model.density:
            factor.fill_(0.0)
        model.density[0][:, 0, 5:9, 6:10] = 4.0  # one dense column in x,y ...
        model.density[3][:, 0, 7:11] = 4.0  # ... over a z range: a dense block inside the box
    model.update_occupancy()
    old_box = (model.box_min.clone(), model.box_max.clone())
    assert model.on_train_step(5) is True
    assert (model.box_min > old_box[0]).any() and (model.box_max < old_box[1]).any()
    assert model.lattice_shape != (17, 17, 17)
    assert model.on_train_step(6) is False


def test_checkpoints_save_load_and_resume_identically_across_an_upsampling(tiny_npz, tmp_path):
    factors = dict(initial_voxels=12**3, final_voxels=16**3, upsample_steps=[2], occupancy_warmup_steps=1,
                   occupancy_update_every=1, density_components=2, color_components=3)  # fmt: skip
    config = dict(
        model="tensorf", model_options=factors, batch_rays=64, log_every=1, val_every=100, device="cpu"
    )
    train(tiny_npz, tmp_path / "whole", TrainConfig(steps=5, checkpoint_every=100, **config))
    train(tiny_npz, tmp_path / "split", TrainConfig(steps=3, checkpoint_every=100, **config))
    train(tiny_npz, tmp_path / "split", TrainConfig(steps=5), resume=True)

    def losses(run):
        lines = (run / "metrics.jsonl").read_text().splitlines()
        return [record["loss"] for record in map(json.loads, lines) if "loss" in record]

    assert losses(tmp_path / "split") == losses(tmp_path / "whole") and len(losses(tmp_path / "whole")) == 5
    whole, split = load_run(tmp_path / "whole", device="cpu"), load_run(tmp_path / "split", device="cpu")
    assert whole.model.lattice_shape == split.model.lattice_shape != (13, 13, 13)
    for name, value in whole.model.state_dict().items():
        assert torch.equal(value, split.model.state_dict()[name]), name


def test_positions_go_through_one_mapping_before_the_lookup():
    model = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=8**3))
    points = torch.tensor([[0.3, 0.1, -0.2], [0.9, -0.5, 0.4]])
    halved = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=8**3))
    halved.load_state_dict(model.state_dict())
    halved.map_positions = lambda positions: 0.5 * positions  # e.g. a contraction for unbounded scenes
    assert torch.allclose(halved.density_at(points), model.density_at(0.5 * points))


# ------------------------------------------------------------------------------- the shared estimator
@pytest.mark.parametrize("which", ["fast", "tensorf"])
def test_the_occupancy_estimator_never_skips_a_point_denser_than_its_threshold(which):
    torch.manual_seed(4)
    if which == "fast":
        model = FastModel(SCENE, FastModelConfig(initial_voxels=12**3, occupancy_min_seen_steps=0))
        with torch.no_grad():
            model.density.normal_(-2.0, 3.0)
    else:
        model = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=12**3))
        with torch.no_grad():
            for factor in model.density:
                factor.normal_(0.0, 0.6)
    model.update_occupancy()
    threshold = model.config.occupancy_alpha_threshold
    points = torch.rand(200_000, 3) * 2 - 1  # the whole box
    alpha = -torch.expm1(-model.density_at(points) * model.step_size)
    occupied = model.occupancy.query(points)
    assert 0.05 < model.occupancy.occupied_fraction() < 0.95  # something to skip, something to keep
    assert occupied[alpha > threshold].all()


def test_the_estimator_takes_a_density_callback_and_bounds_a_multilinear_field_exactly():
    grid = OccupancyGrid(-torch.ones(3), torch.ones(3), (4, 4, 4))
    # sigma = 100 (x + 1), a ramp in x: multilinear, so the vertex max bounds each cell exactly.
    alpha = grid.update(lambda p: 100.0 * (p[:, 0] + 1.0), step_size=0.01, alpha_threshold=0.5)
    assert alpha.shape == (4, 4, 4)
    # 1 - exp(-100 (x + 1) 0.01) > 0.5 iff x > ln(2) - 1 = -0.31: cells whose right face is beyond it.
    assert grid.occupied[:, 0, 0].tolist() == [False, True, True, True]
    grid.update(lambda p: 100.0 * (p[:, 0] + 1.0), step_size=0.01, alpha_threshold=0.5, dilation=1)
    assert grid.occupied[:, 0, 0].tolist() == [True, True, True, True]


# ------------------------------------------------------------------------------------------ distortion
def test_packed_distortion_equals_the_quadratic_formula_per_ray():
    torch.manual_seed(5)
    counts = [3, 0, 5, 1]
    ray_indices = torch.repeat_interleave(torch.arange(4), torch.tensor(counts))
    t = torch.cat([torch.sort(torch.rand(n) * 4 + 2).values for n in counts])
    deltas = torch.rand(t.shape[0]) * 0.1
    weights = torch.rand(t.shape[0]) * 0.3
    expected = 0.0
    for ray in range(4):
        w, s, d = weights[ray_indices == ray], t[ray_indices == ray], deltas[ray_indices == ray]
        expected += float((w[:, None] * w[None, :] * (s[:, None] - s[None, :]).abs()).sum())
        expected += float((w.square() * d).sum()) / 3.0
    distortion = packed_distortion(weights, t, deltas, ray_indices, 4)
    assert float(distortion) == pytest.approx(expected / 4, rel=1e-5)


def test_the_distortion_loss_is_added_when_weighted():
    origins, directions, _ = ring_views(num_views=1, size=4)
    model = TensorVMModel(SCENE, TensorVMConfig(initial_voxels=8**3, occupancy_warmup_steps=0))
    assert model.render_rays(origins, directions, 1.5, 5.0, WHITE, train=True).extra_loss is None
    model.config.distortion_weight = 0.1
    extra = model.render_rays(origins, directions, 1.5, 5.0, WHITE, train=True).extra_loss
    assert extra is not None and float(extra.detach()) > 0
