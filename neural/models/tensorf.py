"""The factorized-grid model (TensoRF, vector-matrix decomposition): a compact alternative to the dense grid.

A field on the box's vertex lattice is written as a sum of R components per axis pair,
    f(x, y, z) = sum_r P^xy_r(x, y) L^z_r(z) + P^xz_r(x, z) L^y_r(y) + P^yz_r(y, z) L^x_r(x),
planes P bilinearly and lines L linearly interpolated, so a lattice of N^3 vertices costs 3 R (N^2 + N) values
instead of N^3. Density: sigma = exp(f_sigma + shift) (as the fast model). Colour: the 3 R_c products of the
appearance factors, mapped by a learned linear basis to spherical-harmonic coefficients (degree 0 or 1) per
RGB channel, c = sigmoid(sum_k coef_k Y_k(d)).

It shares the fast model's machinery: the occupancy grid as density estimator (neural.occupancy), packed
rendering with early termination, the coarse-to-fine schedule that upsamples the factors and refits them to
the occupied box. Positions pass through `map_positions` before the lookup (the identity for bounded
scenes), so a contraction for unbounded scenes plugs in with one change.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor

from neural.models.base import Bounds, RadianceModel, RayBundleOutput
from neural.models.fast import MAX_LOG_DENSITY, grid_shape_for, sh_colour
from neural.occupancy import GridSchedule, OccupancyGrid, render_packed_samples
from neural.rendering import packed_distortion

#: (plane axes, line axis) of the three vector-matrix components.
MODES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))


def identity_positions(positions: Tensor) -> Tensor:
    """The mapping of bounded scenes: world points are the grid's space."""
    return positions


class TensorVMConfig(BaseModel):
    """Factor ranks, lattice sizes, schedule, sampling, regularizers and learning rates of the VM model."""

    model_config = ConfigDict(extra="forbid")

    density_components: int = Field(8, gt=0, description="components R per axis pair of the density")
    color_components: int = Field(24, gt=0, description="components R_c per axis pair of the appearance")
    sh_degree: int = Field(0, ge=0, le=1, description="spherical-harmonic degree of the colour (0: diffuse)")
    initial_voxels: int = Field(64**3, gt=0, description="lattice size (total voxels) at the start")
    final_voxels: int = Field(192**3, gt=0, description="lattice size after the last upsampling")
    upsample_steps: list[int] = Field(
        default_factory=lambda: [100, 250, 450],
        description="steps at which the factors are upsampled and refitted to the occupied box",
    )
    fit_box_to_occupancy: bool = Field(True, description="shrink the lattice to the occupied box")
    box_margin_voxels: float = Field(2.0, ge=0, description="margin around the occupied box, in voxels")
    box_alpha_threshold: float = Field(1e-2, gt=0, lt=1, description="opacity that counts into the box")
    init_std: float = Field(0.1, gt=0, description="standard deviation of the initial factors")
    step_ratio: float = Field(0.5, gt=0, description="sample spacing along rays, in voxels")
    initial_alpha: float = Field(1e-4, gt=0, lt=1, description="opacity of one sample step at f_sigma = 0")
    occupancy_warmup_steps: int = Field(40, ge=0, description="steps during which every cell counts occupied")
    occupancy_update_every: int = Field(16, gt=0, description="steps between occupancy-grid updates")
    occupancy_alpha_threshold: float = Field(1e-3, gt=0, lt=1, description="cells below this are empty")
    transmittance_threshold: float = Field(1e-4, ge=0, lt=1, description="early ray termination")
    color_weight_threshold: float = Field(1e-4, ge=0, lt=1, description="weights below skip the colour")
    distortion_weight: float = Field(0.0, ge=0, description="mip-NeRF 360 distortion loss weight")
    basis_lr_scale: float = Field(0.05, gt=0, description="learning rate of the colour basis / trainer's lr")

    @model_validator(mode="after")
    def _check_schedule(self) -> TensorVMConfig:
        if self.upsample_steps != sorted(self.upsample_steps) or any(s <= 0 for s in self.upsample_steps):
            raise ValueError(f"upsample_steps must be positive and increasing, got {self.upsample_steps}")
        if self.final_voxels < self.initial_voxels:
            raise ValueError("final_voxels must be at least initial_voxels")
        return self


def vm_factors(shape: tuple[int, int, int], components: int, std: float) -> torch.nn.ParameterList:
    """Planes (1,R,N_a,N_b) then lines (1,R,N_c,1) of the three modes, normal(0, std) values."""
    planes = [torch.randn(1, components, shape[a], shape[b]) * std for a, b, _ in MODES]
    lines = [torch.randn(1, components, shape[c], 1) * std for _, _, c in MODES]
    return torch.nn.ParameterList([torch.nn.Parameter(f) for f in planes + lines])


def vm_products(factors: torch.nn.ParameterList, coordinates: Tensor) -> Tensor:
    """P_r(x_a, x_b) L_r(x_c) of every mode and component at coordinates (N,3) in [-1,1]; (N, 3R)."""
    products = []
    for mode, (a, b, c) in enumerate(MODES):
        plane_grid = coordinates[:, [b, a]].reshape(1, 1, -1, 2)  # grid_sample: (x, y) = (last dim, rows)
        line_grid = torch.stack([torch.zeros_like(coordinates[:, c]), coordinates[:, c]], -1)
        plane = F.grid_sample(factors[mode], plane_grid, mode="bilinear", align_corners=True)
        line = F.grid_sample(factors[3 + mode], line_grid.reshape(1, 1, -1, 2), align_corners=True)
        products.append((plane * line)[0, :, 0])
    return torch.cat(products).T


class TensorVMModel(GridSchedule, RadianceModel):
    """Vector-matrix factorized density and appearance over the scene box, with occupancy skipping."""

    model_name: ClassVar[str] = "tensorf"
    # TensoRF's Adam learning rates: 0.02 for the factors, 1e-3 (basis_lr_scale 0.05) for the basis.
    train_defaults: ClassVar[dict[str, Any]] = {
        "steps": 3000,
        "batch_rays": 4096,
        "lr": 0.02,
        "lr_decay": 0.1,
        "lr_decay_steps": 3000,
        "precrop_steps": 0,
    }
    map_positions = staticmethod(identity_positions)

    def __init__(self, scene: Bounds, config: TensorVMConfig | None = None) -> None:
        super().__init__(scene)
        self.config = config or TensorVMConfig()
        box_min = torch.tensor(scene.scene_box_min, dtype=torch.float32)
        box_max = torch.tensor(scene.scene_box_max, dtype=torch.float32)
        shape, voxel_size = grid_shape_for(box_min, box_max, self.config.initial_voxels)
        self.register_buffer("box_min", box_min)
        self.register_buffer("box_max", box_max)
        self.register_buffer("voxel_size", torch.tensor(voxel_size, dtype=torch.float32))
        self.density = vm_factors(shape, self.config.density_components, self.config.init_std)
        self.appearance = vm_factors(shape, self.config.color_components, self.config.init_std)
        num_sh = (self.config.sh_degree + 1) ** 2
        self.basis = torch.nn.Linear(3 * self.config.color_components, 3 * num_sh, bias=False)
        self.occupancy = OccupancyGrid(box_min, box_max, cells_of(shape))
        initial_sigma = -math.log(1.0 - self.config.initial_alpha) / (self.config.step_ratio * voxel_size)
        self.density_shift = math.log(initial_sigma)

    # ---------------------------------------------------------------------------------------- fields
    @property
    def step_size(self) -> float:
        return self.config.step_ratio * float(self.voxel_size)

    @property
    def lattice_shape(self) -> tuple[int, int, int]:
        """Vertices per axis of the lattice the factors live on."""
        (_, _, x, y), (_, _, _, z) = self.density[0].shape, self.density[1].shape
        return int(x), int(y), int(z)

    def _coordinates(self, positions: Tensor) -> Tensor:
        """Lattice coordinates in [-1,1] of world points (N,3), through map_positions."""
        return (self.map_positions(positions) - self.box_min) / (self.box_max - self.box_min) * 2.0 - 1.0

    def density_at(self, positions: Tensor) -> Tensor:
        """sigma(x) = exp(f_sigma(x) + shift), f_sigma the sum of the density products; (N,)."""
        raw = vm_products(self.density, self._coordinates(positions)).sum(-1)
        return torch.exp((raw + self.density_shift).clamp_max(MAX_LOG_DENSITY))

    def lattice_density(self) -> Tensor:
        """sigma at every lattice vertex, (X,Y,Z): the products as outer products (no interpolation)."""
        planes, lines = self.density[:3], self.density[3:]
        raw = (
            torch.einsum("rxy,rz->xyz", planes[0][0], lines[0][0, :, :, 0])
            + torch.einsum("rxz,ry->xyz", planes[1][0], lines[1][0, :, :, 0])
            + torch.einsum("ryz,rx->xyz", planes[2][0], lines[2][0, :, :, 0])
        )
        return torch.exp((raw + self.density_shift).clamp_max(MAX_LOG_DENSITY))

    def color_at(self, positions: Tensor, directions: Tensor) -> Tensor:
        """c(x, d) = sigmoid(sum_k (B f_c(x))_k Y_k(d)) per channel; (N,3)."""
        features = vm_products(self.appearance, self._coordinates(positions))
        return sh_colour(self.basis(features), directions, self.config.sh_degree)

    # ------------------------------------------------------------------------------------- rendering
    def render_rays(
        self,
        origins: Tensor,
        directions: Tensor,
        near: float,
        far: float,
        background: Tensor,
        train: bool,
        generator: torch.Generator | None = None,
    ) -> RayBundleOutput:
        """Packed volume rendering of the occupied samples of each ray; the distortion loss when training."""
        jitter = torch.rand(origins.shape[0], generator=generator, device=origins.device) if train else None
        samples = self.occupancy.sample(
            origins, directions, near, far, self.step_size, jitter, self.density_at,
            self.config.transmittance_threshold,
        )  # fmt: skip
        out = render_packed_samples(
            samples, directions, self.density_at, self.color_at, background,
            self.config.color_weight_threshold,
        )  # fmt: skip
        extra_loss = None
        if train and self.config.distortion_weight > 0:
            distortion = packed_distortion(
                out.weights, samples.t, samples.deltas, samples.ray_indices, origins.shape[0]
            )
            extra_loss = self.config.distortion_weight * distortion
        return RayBundleOutput(rgb=out.rgb, depth=out.depth, opacity=out.opacity, extra_loss=extra_loss)

    # -------------------------------------------------------------------------------------- training
    @torch.no_grad()
    def update_occupancy(self) -> Tensor:
        """Occupancy of the lattice's cells from the density at their vertices; per-cell opacity bound.

        Inside a cell each product (bilinear plane times linear line) is trilinear, so the field is too and
        the max over the cell's vertices bounds every sample in it: the skipping is conservative.
        """
        return self.occupancy.update(
            self.lattice_density(), self.step_size, self.config.occupancy_alpha_threshold
        )

    @torch.no_grad()
    def _upsample(self, stage: int) -> None:
        """Resample the factors at the voxel count of `stage` over the (refitted) box; occupancy follows."""
        num_stages = len(self.config.upsample_steps)
        ratio = self.config.final_voxels / self.config.initial_voxels
        num_voxels = round(self.config.initial_voxels * ratio ** (stage / num_stages))
        box_min, box_max = self.box_min.clone(), self.box_max.clone()
        if self.config.fit_box_to_occupancy and self.occupancy.occupied_fraction() < 1.0:
            alpha = self.update_occupancy()
            dense = self.occupancy.occupied & (alpha > self.config.box_alpha_threshold)
            cells = dense.nonzero()
            if cells.numel():
                cell_size = (self.box_max - self.box_min) / torch.tensor(dense.shape, device=cells.device)
                margin = self.config.box_margin_voxels * float(self.voxel_size) + cell_size
                box_min = torch.maximum(self.box_min + cells.amin(0) * cell_size - margin, self.box_min)
                box_max = torch.minimum(self.box_min + (cells.amax(0) + 1) * cell_size + margin, self.box_max)
        shape, voxel_size = grid_shape_for(box_min, box_max, num_voxels)
        old_min, old_max = self.box_min, self.box_max
        for factors in (self.density, self.appearance):
            for index, factor in enumerate(factors):
                axes = MODES[index][:2] if index < 3 else (MODES[index - 3][2],)
                factors[index] = torch.nn.Parameter(
                    resample_factor(factor, axes, (old_min, old_max), (box_min, box_max), shape)
                )
        self.box_min, self.box_max = box_min, box_max
        self.voxel_size = torch.tensor(voxel_size, dtype=torch.float32, device=box_min.device)
        self.occupancy.reset(box_min, box_max, cells_of(shape))

    def _load_from_state_dict(
        self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any
    ) -> None:
        """Take the factor shapes of the checkpoint first: upsampling changes them during training."""
        for name in ("density", "appearance"):
            factors = getattr(self, name)
            for index, factor in enumerate(factors):
                stored = state_dict.get(f"{prefix}{name}.{index}")
                if stored is not None and stored.shape != factor.shape:
                    factors[index] = torch.nn.Parameter(factor.new_empty(stored.shape))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """The factors at `lr`, the colour basis at lr * basis_lr_scale."""
        return [
            {"params": [*self.density, *self.appearance], "lr": lr, "name": "factors"},
            {"params": list(self.basis.parameters()), "lr": lr * self.config.basis_lr_scale, "name": "basis"},
        ]


def cells_of(shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """Cells per axis of a lattice of `shape` vertices."""
    return shape[0] - 1, shape[1] - 1, shape[2] - 1


def resample_factor(
    factor: Tensor,
    axes: tuple[int, ...],
    old_box: tuple[Tensor, Tensor],
    new_box: tuple[Tensor, Tensor],
    shape: tuple[int, int, int],
) -> Tensor:
    """A plane (1,R,N_a,N_b) or line (1,R,N_c,1) over old_box, resampled on the lattice `shape` of new_box."""
    grids = []
    for axis in axes:
        world = torch.linspace(float(new_box[0][axis]), float(new_box[1][axis]), shape[axis])
        grids.append((world - float(old_box[0][axis])) / float(old_box[1][axis] - old_box[0][axis]) * 2 - 1)
    if len(grids) == 1:
        grids.append(torch.zeros(1))
    rows, columns = torch.meshgrid(grids[0], grids[1], indexing="ij")
    grid = torch.stack([columns, rows], dim=-1)[None].to(factor.device)
    return F.grid_sample(factor, grid, mode="bilinear", align_corners=True).contiguous()
