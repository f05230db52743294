"""The fast model: explicit voxel grids (DVGO / Plenoxels style) that train in minutes on a CPU.

Density: a dense grid of raw values, trilinearly interpolated, then sigma = exp(raw + shift) (an exponential,
so that Adam's additive steps move density by factors: empty and opaque are a few steps apart).
Colour: a dense grid of spherical-harmonic coefficients (degree 0 or 1) per RGB channel, interpolated and
then c = sigmoid(sum_k coef_k Y_k(d)). With degree 1 the three view-dependent coefficients per channel may
live on a grid `view_grid_stride` times coarser per axis (view dependence varies slowly in space; the dense
per-step costs, gradient and Adam over every voxel, grow with the channels of the full-resolution grids).
No network: a sample costs two or three `grid_sample` calls.
Speed comes from (1) an occupancy grid, recomputed from the density grid itself, that skips empty space,
(2) a coarse-to-fine schedule that upsamples the grids and refits them to the occupied box, with the sample
spacing tied to the voxel size, and (3) early ray termination and skipping the colour of samples with
negligible weight. Everything is learned from RGB images alone; no masks, no assumed background.
Unbounded scenes (`Bounds.unbounded`): the grids cover contracted space (neural.contraction: the scene
box is kept as it is, everything beyond is squeezed into a shell of thickness `shell_thickness`), points are
contracted before every grid lookup, and rays are sampled at equal steps in contracted space
(neural.sampling.contracted_space_samples: uniform in the box, disparity-linear beyond it); the samples in
the box come first, with strides of empty cells skipped and in rounds that stop at opaque surfaces, and the
shell is sampled only for the rays still visible behind the box.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor

from neural.contraction import InnerBox, uncontracted_norm
from neural.models.base import Bounds, RadianceModel, RayBundleOutput
from neural.occupancy import (
    GridSchedule,
    OccupancyGrid,
    PackedSamples,
    cell_alpha_bound,
    drop_occluded,
    drop_occluded_after,
    opaque_depth,
    render_packed_samples,
)
from neural.rendering import SampleWeights, packed_distortion
from neural.sampling import ContractedRays, contracted_rays, contracted_steps
from neural.trilinear import trilinear

#: Real spherical-harmonic constants, degrees 0 and 1.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
#: Upper clamp of log density: exp(15) per unit length is opaque within any voxel.
MAX_LOG_DENSITY = 15.0
#: An unbounded scene's samples in the box come in rounds of each ray's first strides (of occupied blocks),
#: this many, then twice as many each round, each round for the rays still visible.
FIRST_ROUND_STRIDES = 2


#: Fields added after the first stored configs, with the behaviour a stored config without them had.
LEGACY_VALUES: dict[str, Any] = {"view_grid_stride": 1, "inner_region": "cube", "shell_thickness": 1.0}
#: Every later field (those without a legacy value change training only, not a trained model).
LATER_FIELDS = {*LEGACY_VALUES, "shell_initial_alpha", "occupancy_min_seen_steps", "occupancy_seen_occluded"}


class FastModelConfig(BaseModel):
    """Grid sizes, schedule, sampling and learning rates of the fast model."""

    model_config = ConfigDict(extra="forbid")

    initial_voxels: int = Field(32**3, gt=0, description="grid size (total voxels) at the start")
    final_voxels: int = Field(128**3, gt=0, description="grid size after the last upsampling")
    upsample_steps: list[int] = Field(
        default_factory=lambda: [60, 200, 400],
        description="steps at which the grids are upsampled (geometric voxel counts) and refitted to the "
        "occupied box",
    )
    fit_box_to_occupancy: bool = Field(
        True, description="shrink the grids to the occupied box when upsampling"
    )
    box_margin_voxels: float = Field(2.0, ge=0, description="margin around the occupied box, in voxels")
    box_alpha_threshold: float = Field(
        1e-2, gt=0, lt=1, description="opacity per sample step that counts a cell into the refitted box"
    )
    # Degree 1 on a grid twice as coarse: ~+1.7 dB on held-out lego views over diffuse colour at equal CPU
    # time (bench_nerf.py, benchmarks/RESULTS.md); a grid of all 12 coefficients costs 2.9x time per step.
    sh_degree: int = Field(1, ge=0, le=1, description="spherical-harmonic degree of the colour (0: diffuse)")
    view_grid_stride: int = Field(
        2,
        ge=1,
        description="with sh_degree 1: the degree-1 (view-dependent) coefficients live on a grid this many "
        "times coarser per axis than the diffuse colour (1: one colour grid of all coefficients)",
    )
    step_ratio: float = Field(0.5, gt=0, description="sample spacing along rays, in voxels")
    initial_alpha: float = Field(1e-4, gt=0, lt=1, description="opacity of one sample step at initialization")
    # The far backdrop starts a little denser than the inner box: with 1e-4 (= initial_alpha) the boxes'
    # far sphere (tests/neural) was fitted as floaters 1.5 units in front of the cameras; with 1e-2 it lands
    # in the shell (depth ~7), while the shell stays translucent (a uniform raw density made it opaque).
    shell_initial_alpha: float = Field(
        1e-2,
        gt=0,
        lt=1,
        description="unbounded scenes: opacity of one sample step in the contracted shell at initialization",
    )
    # A flat region of interest (a facade and its square) fills a fraction of its enclosing cube; a thin
    # shell leaves the inner box most voxels (1 / (1 + w)^3 of them; a half with w = 0.25).
    inner_region: Literal["box", "cube"] = Field(
        "box",
        description="unbounded scenes: the region kept uncontracted is the scene box itself (voxels as long "
        "along every axis) or the smallest cube holding it",
    )
    shell_thickness: float = Field(
        0.25, gt=0, description="unbounded scenes: thickness of the contracted shell, in inner half-sides"
    )
    occupancy_warmup_steps: int = Field(40, ge=0, description="steps during which every cell counts occupied")
    occupancy_update_every: int = Field(16, gt=0, description="steps between occupancy-grid updates")
    occupancy_alpha_threshold: float = Field(
        1e-3, gt=0, lt=1, description="a cell is empty when no sample step in it can reach this opacity"
    )
    occupancy_min_seen_steps: int = Field(
        8, ge=0, description="a cell stays occupied until training evaluated samples in it on this many steps"
    )
    occupancy_seen_occluded: bool = Field(
        True,
        description="samples behind opaque surfaces (dropped by early ray termination) count as seen: the "
        "occluded cells empty too, instead of staying occupied and costing a density lookup every step",
    )
    transmittance_threshold: float = Field(
        1e-4, ge=0, lt=1, description="samples behind this transmittance are dropped (early ray termination)"
    )
    color_weight_threshold: float = Field(
        1e-4, ge=0, lt=1, description="samples below this compositing weight skip the colour lookup"
    )
    tv_density_weight: float = Field(0.0, ge=0, description="total-variation weight on the density grid")
    tv_color_weight: float = Field(0.0, ge=0, description="total-variation weight on the colour grid")
    distortion_weight: float = Field(0.0, ge=0, description="mip-NeRF 360 distortion loss weight")
    color_lr_scale: float = Field(
        1 / 3, gt=0, description="learning rate of the colour grid relative to the trainer's (density) lr"
    )

    @model_validator(mode="before")
    @classmethod
    def _stored_before_later_fields(cls, data: Any) -> Any:
        """A complete config stored (in a checkpoint) before a field existed gets the value that field's
        behaviour had then (`LEGACY_VALUES`): one colour grid, a cube with mip-NeRF 360's shell."""
        if not isinstance(data, dict) or not set(cls.model_fields) - LATER_FIELDS <= set(data):
            return data
        return {**{name: value for name, value in LEGACY_VALUES.items() if name not in data}, **data}

    @model_validator(mode="after")
    def _check_schedule(self) -> FastModelConfig:
        if self.upsample_steps != sorted(self.upsample_steps) or any(s <= 0 for s in self.upsample_steps):
            raise ValueError(f"upsample_steps must be positive and increasing, got {self.upsample_steps}")
        if self.final_voxels < self.initial_voxels:
            raise ValueError("final_voxels must be at least initial_voxels")
        return self


def grid_shape_for(box_min: Tensor, box_max: Tensor, num_voxels: int) -> tuple[tuple[int, int, int], float]:
    """Vertices per axis n_k = round(extent_k / s) + 1 for the voxel size s = (volume / num_voxels)^(1/3)."""
    extent = (box_max - box_min).double()
    voxel_size = float((extent.prod() / num_voxels) ** (1.0 / 3.0))
    shape = tuple(max(2, round(float(e) / voxel_size) + 1) for e in extent)
    return (shape[0], shape[1], shape[2]), voxel_size


def grid_vertices(box_min: Tensor, box_max: Tensor, shape: tuple[int, int, int]) -> Tensor:
    """The (X*Y*Z, 3) vertices of a grid of `shape` vertices spanning the box, in (X,Y,Z) order."""
    axes = [
        torch.linspace(float(low), float(high), n, device=box_min.device)
        for low, high, n in zip(box_min, box_max, shape, strict=True)
    ]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """Real SH basis Y_k(d) for unit directions (N,3): (N,1) for degree 0, (N,4) for degree 1."""
    constant = torch.full_like(directions[:, :1], SH_C0)
    if degree == 0:
        return constant
    x, y, z = directions.unbind(-1)
    return torch.cat([constant, torch.stack([-SH_C1 * y, SH_C1 * z, -SH_C1 * x], dim=-1)], dim=-1)


def sh_colour(coefficients: Tensor, directions: Tensor, degree: int) -> Tensor:
    """c = sigmoid(sum_k coef_k Y_k(d)) per channel, from coefficients (N, 3 * num_sh); (N,3)."""
    basis = sh_basis(directions, degree)
    return torch.sigmoid((coefficients.reshape(-1, 3, basis.shape[1]) * basis[:, None, :]).sum(-1))


def add_total_variation_gradient(grid: Tensor, gradient: Tensor, weight: float) -> None:
    """gradient += weight * d/dv TV(v), TV = sum over the axes of the mean (v_k+1 - v_k)^2 along that axis.

    Along an axis with n differences, each difference d_k = v_k+1 - v_k adds 2 d_k / n to v_k+1's gradient and
    subtracts it from v_k's. Written into the gradient in place (after the backward pass), not through
    autograd: the loss is quadratic, so the gradient needs only the differences, and autograd's version (a
    zero gradient of the whole grid per shifted slice, then the sum into .grad) cost 38 ms of a fountain-P11
    step on its final 2M-voxel grids, against 26 ms now (one thread; benchmarks/RESULTS.md)."""
    for axis in (2, 3, 4):
        length = grid.shape[axis] - 1
        difference = grid.narrow(axis, 1, length) - grid.narrow(axis, 0, length)
        scale = 2.0 * weight / difference.numel()
        gradient.narrow(axis, 1, length).add_(difference, alpha=scale)
        gradient.narrow(axis, 0, length).sub_(difference, alpha=scale)


class FastModel(GridSchedule, RadianceModel):
    """Density and SH-colour voxel grids over the scene box with occupancy-based empty-space skipping."""

    model_name: ClassVar[str] = "fast"
    supports_unbounded: ClassVar[bool] = True
    packs_samples: ClassVar[bool] = True
    # Grids take large Adam steps (DVGO uses 0.1); the raw density is a log-density, so 0.3 per step moves
    # sigma by ~35%. steps: the default length when neither steps nor minutes is given.
    train_defaults: ClassVar[dict[str, Any]] = {
        "steps": 3000,
        "batch_rays": 4096,
        "lr": 0.3,
        "lr_decay": 0.1,
        "lr_decay_steps": 3000,
        "precrop_steps": 0,
    }

    def __init__(self, scene: Bounds, config: FastModelConfig | None = None) -> None:
        super().__init__(scene)
        self.config = config or FastModelConfig()
        # Grid coordinates: the world (scene frame) if bounded, contracted space for an unbounded scene.
        self.inner_box = (
            InnerBox.around(
                scene.scene_box_min, scene.scene_box_max, cube=self.config.inner_region == "cube",
                shell=self.config.shell_thickness,
            )
            if scene.unbounded
            else None
        )  # fmt: skip
        if self.inner_box is None:
            box_min = torch.tensor(scene.scene_box_min, dtype=torch.float32)
            box_max = torch.tensor(scene.scene_box_max, dtype=torch.float32)
        else:
            box_max = self.inner_box.contracted_extent
            box_min = -box_max
        shape, voxel_size = grid_shape_for(box_min, box_max, self.config.initial_voxels)
        self.register_buffer("box_min", box_min)
        self.register_buffer("box_max", box_max)
        self.register_buffer("voxel_size", torch.tensor(voxel_size, dtype=torch.float32))
        self.density = torch.nn.Parameter(self._initial_density(box_min, box_max, shape))
        self.color = torch.nn.Parameter(torch.zeros((1, 3 * self.num_color_sh, *shape)))
        self.color_view = (
            torch.nn.Parameter(torch.zeros((1, 3 * (self.num_sh - 1), *self.view_grid_shape(shape))))
            if self.num_color_sh < self.num_sh
            else None
        )
        cells = (shape[0] - 1, shape[1] - 1, shape[2] - 1)
        self.occupancy = OccupancyGrid(box_min, box_max, cells)
        # sigma = exp(raw + shift): raw = 0 gives one sample step the opacity `initial_alpha`.
        initial_sigma = -math.log(1.0 - self.config.initial_alpha) / (self.unit_length * self.step_size)
        self.density_shift = math.log(initial_sigma)

    # ----------------------------------------------------------------------------------------- grids
    def _initial_density(self, box_min: Tensor, box_max: Tensor, shape: tuple[int, int, int]) -> Tensor:
        """Raw density (1,1,X,Y,Z) giving every sample step the opacity `initial_alpha` (raw 0), in the shell
        of contracted space `shell_initial_alpha`: there a step is r^2 / w longer in the world
        (`_shell_stretch`), so raw is -log(r^2 / w) + log(sigma_shell / sigma_inner).

        A uniform raw density would make the shell's far steps opaque from the start: every ray would end in
        the shell, the photos would be explained as a far backdrop, and no foreground would form.
        """
        if self.inner_box is None:
            return torch.zeros((1, 1, *shape))
        rho = self.inner_box.contracted_norm(grid_vertices(box_min, box_max, shape))
        config = self.config
        shell = math.log(math.log1p(-config.shell_initial_alpha) / math.log1p(-config.initial_alpha))
        raw = torch.where(rho > 1.0, shell - self._shell_stretch(rho).log(), 0.0)
        return raw.reshape(1, 1, *shape)

    def _shell_stretch(self, rho: Tensor) -> Tensor:
        """r^2 / w at contracted max norms rho > 1 (1 inside): how much longer in the world a step in grid
        coordinates is there than inside the box (r: the uncontracted norm, capped at the far bound)."""
        box = self.inner_box
        far_unit = self.scene.far / min(box.half_sides)
        stretch = uncontracted_norm(rho, box.shell, far_unit).square() / box.shell
        return torch.where(rho > 1.0, stretch, 1.0)

    @property
    def num_sh(self) -> int:
        return (self.config.sh_degree + 1) ** 2

    @property
    def num_color_sh(self) -> int:
        """SH coefficients per channel in `color` (the rest, if any, are in the coarser `color_view`)."""
        return 1 if self.config.view_grid_stride > 1 else self.num_sh

    def view_grid_shape(self, shape: tuple[int, int, int]) -> tuple[int, int, int]:
        """Vertices per axis of the view-dependent grid over the same box: (n - 1) / stride + 1, rounded."""
        stride = self.config.view_grid_stride
        x, y, z = (max(2, round((n - 1) / stride) + 1) for n in shape)
        return x, y, z

    @property
    def step_size(self) -> float:
        """Sample spacing in grid coordinates (world units times unit_length for an unbounded scene)."""
        return self.config.step_ratio * float(self.voxel_size)

    @property
    def unit_length(self) -> float:
        """World length of one grid-coordinate unit where space is not contracted."""
        return 1.0 if self.inner_box is None else self.inner_box.scale

    def to_grid_space(self, positions: Tensor) -> Tensor:
        """World points (N,3) -> grid coordinates: as they are, or contracted for an unbounded scene."""
        return positions if self.inner_box is None else self.inner_box.contract(positions)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        _, _, x, y, z = self.density.shape
        return int(x), int(y), int(z)

    def _sample_grid(self, grid: Tensor, positions: Tensor) -> Tensor:
        """Trilinear interpolation of a (1,C,X,Y,Z) grid over the box at grid-space points (N,3); (N,C)."""
        return trilinear(grid, (positions - self.box_min) / (self.box_max - self.box_min) * 2.0 - 1.0)

    def activate_density(self, raw: Tensor) -> Tensor:
        """sigma = exp(min(raw + shift, MAX_LOG_DENSITY)) >= 0."""
        return torch.exp((raw + self.density_shift).clamp_max(MAX_LOG_DENSITY))

    def density_at(self, positions: Tensor) -> Tensor:
        """sigma(x) = exp(interp(raw)(x) + shift) at world points (N,3); (N,)."""
        return self.grid_density(self.to_grid_space(positions))

    def grid_density(self, grid_positions: Tensor) -> Tensor:
        """sigma at grid-space points (N,3) (contracted for an unbounded scene); (N,)."""
        return self.activate_density(self._sample_grid(self.density, grid_positions)[:, 0])

    def color_at(self, positions: Tensor, directions: Tensor) -> Tensor:
        """c(x, d) = sigmoid(sum_k coef_k(x) Y_k(d)) per channel; (N,3)."""
        grid_positions = self.to_grid_space(positions)
        coefficients = self._sample_grid(self.color, grid_positions)
        if self.color_view is not None:  # per channel: the diffuse coefficient, then the coarse degree-1 ones
            view = self._sample_grid(self.color_view, grid_positions).reshape(-1, 3, self.num_sh - 1)
            coefficients = torch.cat([coefficients[:, :, None], view], dim=-1).reshape(-1, 3 * self.num_sh)
        return sh_colour(coefficients, directions, self.config.sh_degree)

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
        """Packed volume rendering of the occupied samples of each ray (see module docstring)."""
        jitter = torch.rand(origins.shape[0], generator=generator, device=origins.device) if train else None
        samples = self._occupied_samples(origins, directions, near, far, jitter, train)
        out = render_packed_samples(
            samples, directions, self.density_at, self.color_at, background,
            self.config.color_weight_threshold,
        )  # fmt: skip
        if train and not self.config.occupancy_seen_occluded:
            self.occupancy.mark_seen(self.to_grid_space(samples.positions))
        extra_loss = None
        if train and self.config.distortion_weight > 0:
            extra_loss = self.config.distortion_weight * packed_distortion(
                out.weights, samples.t, samples.deltas, samples.ray_indices, origins.shape[0]
            )
        weights = SampleWeights(out.weights, samples.t, samples.ray_indices) if train else None
        return RayBundleOutput(
            rgb=out.rgb, depth=out.depth, opacity=out.opacity, extra_loss=extra_loss, samples=weights
        )

    def _occupied_samples(
        self, origins: Tensor, directions: Tensor, near: float, far: float, jitter: Tensor | None, train: bool
    ) -> PackedSamples:
        """Samples in occupied cells (world units), marched through the box or spaced for contraction, then
        early ray termination (samples behind transmittance_threshold dropped). Training marks the cells of
        the samples before early termination seen (with occupancy_seen_occluded)."""
        threshold = self.config.transmittance_threshold
        mark_seen = train and self.config.occupancy_seen_occluded
        box = self.inner_box
        if box is None:
            samples = self.occupancy.march(origins, directions, near, far, self.step_size, jitter)
            if mark_seen:
                self.occupancy.mark_seen(samples.positions)
            return drop_occluded(samples, origins.shape[0], self.density_at, threshold)
        return self._contracted_samples(origins, directions, near, far, jitter, mark_seen)

    def _contracted_samples(
        self, origins: Tensor, directions: Tensor, near: float, far: float, jitter: Tensor | None,
        mark_seen: bool,
    ) -> PackedSamples:
        """`_occupied_samples` of an unbounded scene: the samples spaced for contraction, in two parts.

        First those before each ray leaves the inner box, where grid coordinates are the scaled world and a
        ray is straight: strides through blocks of empty cells are skipped unseen, as the bounded march does,
        and the strides kept are sampled in rounds (each ray's first 2, next 4, next 8, ...), each round only
        for the rays still visible. Then, for the rays still visible, those in the contracted shell beyond
        it. A photo's rays mostly end at a surface inside the box: neither the occupied cells behind it
        (density that total variation spreads where no ray sees) nor the shell behind it cost anything.
        The samples kept are those of sampling every step, testing its cell and terminating in one pass.
        """
        box, step, grid = self.inner_box, self.step_size, self.occupancy
        scale, num_rays, device = box.scale, origins.shape[0], origins.device
        scaled = box.to_scaled(origins)
        rays = contracted_rays(scaled, directions, near / scale, far / scale, box.extent(device), box.shell)
        if jitter is None:
            jitter = torch.full((num_rays,), 0.5, device=device, dtype=origins.dtype)
        num_steps, inside_steps = rays.num_steps(step), rays.steps_before_exit(step)
        opaque = opaque_depth(self.config.transmittance_threshold)

        # Part 1: one test per stride of steps_per_block steps; a stride wholly inside the box is tested at
        # its start, one reaching outside it is kept.
        per_block = grid.steps_per_block(step)
        num_blocks = (inside_steps + per_block - 1) // per_block
        block = torch.arange(int(num_blocks.max()) if num_rays else 0, device=device)
        ray_index, block_index = (block[None, :] < num_blocks[:, None]).nonzero(as_tuple=True)
        block_s = rays.s_near[ray_index] + (block_index * per_block).to(scaled.dtype) * step
        inside = (block_s >= 0) & (block_s + per_block * step <= (rays.t_exit - rays.t_enter)[ray_index])
        block_t = (rays.t_enter[ray_index] + block_s)[:, None]
        keep = ~inside
        keep[inside] = grid.block_may_be_occupied(
            scaled[ray_index[inside]] + directions[ray_index[inside]] * block_t[inside]
        )
        ray_index, block_index = ray_index[keep], block_index[keep]
        counts = torch.bincount(ray_index, minlength=num_rays)
        rank = torch.arange(ray_index.numel(), device=device) - (counts.cumsum(0) - counts)[ray_index]
        depth = torch.zeros(num_rays, dtype=scaled.dtype, device=device)
        parts, occupied, low, high = [], [], 0, FIRST_ROUND_STRIDES
        while ray_index.numel() and low <= int(rank.max()):
            chosen = (rank >= low) & (rank < high) & (depth < opaque)[ray_index]
            step_index = block_index[chosen, None] * per_block + torch.arange(per_block, device=device)
            chosen_rays = ray_index[chosen, None].expand_as(step_index)
            valid = step_index < inside_steps[chosen_rays]
            part, depth = self._terminated(
                rays, scaled, directions, chosen_rays[valid], step_index[valid], jitter, occupied, depth
            )
            parts.append(part)
            low, high = high, high + 2 * (high - low)

        # Part 2: the steps beyond the box of the rays still visible.
        beyond = torch.where(depth < opaque, num_steps - inside_steps, 0)
        offset = torch.arange(int(beyond.max()) if num_rays else 0, device=device)
        ray_index, step_offset = (offset[None, :] < beyond[:, None]).nonzero(as_tuple=True)
        step_index = inside_steps[ray_index] + step_offset
        parts.append(
            self._terminated(rays, scaled, directions, ray_index, step_index, jitter, occupied, depth)[0]
        )
        if mark_seen:  # once per step, for the cells of all parts
            self.occupancy.mark_seen(torch.cat(occupied))

        # All parts sorted by ray (a ray's parts come in order along it), in world units.
        ray_indices, t, deltas = (torch.cat(field) for field in list(zip(*parts, strict=True))[:3])
        order = torch.sort(ray_indices, stable=True).indices
        ray_indices, t, deltas = ray_indices[order], t[order], deltas[order]
        world = origins[ray_indices] + directions[ray_indices] * t[:, None]
        return PackedSamples(ray_indices, t, deltas, world)

    def _terminated(
        self, rays: ContractedRays, scaled: Tensor, directions: Tensor, ray_index: Tensor, step_index: Tensor,
        jitter: Tensor, occupied: list[Tensor], start_depth: Tensor | None,
    ) -> tuple[PackedSamples, Tensor]:
        """The samples `step_index` of rays `ray_index` (sorted by ray then step) in occupied cells and in
        front of the transmittance threshold, behind start_depth (R,); t and deltas in world units, positions
        in grid coordinates. Also each ray's optical depth after them (see drop_occluded_after). The grid
        positions of the samples in occupied cells are appended to `occupied`."""
        box = self.inner_box
        unit = contracted_steps(
            rays, scaled, directions, ray_index, step_index, self.step_size, jitter, box.shell
        )
        grid_positions = box.contract_scaled(unit.positions)
        keep = self.occupancy.query(grid_positions)
        occupied.append(grid_positions[keep])
        # Early termination looks the density up at the contracted points it has (no second contraction).
        return drop_occluded_after(
            PackedSamples(unit.ray_indices[keep], unit.t[keep] * box.scale, unit.deltas[keep] * box.scale,
                          occupied[-1]),
            scaled.shape[0], self.grid_density, self.config.transmittance_threshold, start_depth,
        )  # fmt: skip

    @torch.no_grad()
    def add_regularizer_gradients(self) -> None:
        """Total variation on the density and diffuse-colour grids (`tv_density_weight`, `tv_color_weight`),
        added to their gradients (`add_total_variation_gradient`)."""
        for grid, weight in ((self.density, self.config.tv_density_weight),
                             (self.color, self.config.tv_color_weight)):
            if weight > 0:
                if grid.grad is None:
                    grid.grad = torch.zeros_like(grid)
                add_total_variation_gradient(grid, grid.grad, weight)

    # -------------------------------------------------------------------------------------- training
    @torch.no_grad()
    def update_occupancy(self) -> None:
        """A cell is occupied iff 1 - exp(-max sigma over its 8 vertices * step) exceeds the threshold.

        The occupancy cells are the grid's voxels and sigma is monotonic in the interpolated raw density, so
        the max over a cell's vertices bounds every sample inside it: no skipped sample can be denser than
        the threshold. The step is the longest world length a sample stands for in the cell
        (`_cell_world_steps`: longer in the outer shell of contracted space). Cells that training has not
        rendered samples in on occupancy_min_seen_steps steps stay occupied.
        """
        vertex_sigma = self.activate_density(self.density)[0, 0]
        self.occupancy.update(
            vertex_sigma, self._cell_world_steps(), self.config.occupancy_alpha_threshold,
            min_seen_steps=self.config.occupancy_min_seen_steps,
        )  # fmt: skip

    def _cell_alpha(self) -> Tensor:
        """Upper bound of one sample step's opacity in each cell: from the max sigma of its 8 vertices."""
        return cell_alpha_bound(self.activate_density(self.density)[0, 0], self._cell_world_steps())

    def _cell_world_steps(self) -> float | Tensor:
        """The longest world length a sample stands for in each cell (X-1,Y-1,Z-1), or one number.

        Contracted space: a step ds at contracted max norm rho > 1 is about r^2 ds / w long in the world
        (`_shell_stretch`); taken at each cell's outer corner, and capped at the far end.
        """
        if self.inner_box is None:
            return self.step_size
        resolution = torch.tensor(self.occupancy.resolution, device=self.density.device)
        extent = self.inner_box.extent(self.density.device)
        axes = [
            torch.linspace(float(low), float(high), int(n) + 1, device=self.density.device) / half
            for low, high, n, half in zip(self.box_min, self.box_max, resolution, extent, strict=True)
        ]  # in contracted unit coordinates
        outer = [torch.maximum(axis[:-1].abs(), axis[1:].abs()) for axis in axes]
        rho = torch.maximum(outer[0][:, None, None], outer[1][None, :, None])
        rho = torch.maximum(rho, outer[2][None, None, :])
        return self.step_size * self.unit_length * self._shell_stretch(rho)

    def _dense_box(self) -> tuple[Tensor, Tensor] | None:
        """World box of the occupied cells at least box_alpha_threshold opaque (None: none is, or warm-up)."""
        if self.occupancy.occupied_fraction() == 1.0:
            return None  # still warming up: nothing learned about where the scene is
        dense = OccupancyGrid(self.box_min, self.box_max, self.occupancy.resolution).to(self.box_min.device)
        dense.set_occupied(self.occupancy.occupied & (self._cell_alpha() > self.config.box_alpha_threshold))
        return dense.occupied_box()

    @torch.no_grad()
    def _upsample(self, stage: int) -> None:
        """Resample the grids at the voxel count of `stage` over the (refitted) box; occupancy follows."""
        num_stages = len(self.config.upsample_steps)
        ratio = self.config.final_voxels / self.config.initial_voxels
        num_voxels = round(self.config.initial_voxels * ratio ** (stage / num_stages))
        box_min, box_max = self.box_min.clone(), self.box_max.clone()
        fitted = self._dense_box() if self.config.fit_box_to_occupancy else None
        if fitted is not None:
            margin = self.config.box_margin_voxels * float(self.voxel_size)
            box_min = torch.maximum(fitted[0] - margin, self.box_min)
            box_max = torch.minimum(fitted[1] + margin, self.box_max)
        shape, voxel_size = grid_shape_for(box_min, box_max, num_voxels)
        density = self._resampled(self.density, box_min, box_max, shape)
        color = self._resampled(self.color, box_min, box_max, shape)
        if self.color_view is not None:
            view_shape = self.view_grid_shape(shape)
            self.color_view = torch.nn.Parameter(
                self._resampled(self.color_view, box_min, box_max, view_shape)
            )
        self.box_min, self.box_max = box_min, box_max
        self.voxel_size = torch.tensor(voxel_size, dtype=torch.float32, device=self.density.device)
        self.density = torch.nn.Parameter(density)
        self.color = torch.nn.Parameter(color)
        self.occupancy.reset(box_min, box_max, (shape[0] - 1, shape[1] - 1, shape[2] - 1))

    def _resampled(
        self, grid: Tensor, box_min: Tensor, box_max: Tensor, shape: tuple[int, int, int]
    ) -> Tensor:
        """The (1,C,X,Y,Z) grid (over the current box) interpolated at the vertices of `shape` over a box."""
        vertices = grid_vertices(box_min.to(grid.device), box_max.to(grid.device), shape)
        return self._sample_grid(grid, vertices).T.reshape(1, -1, *shape).contiguous()

    def _load_from_state_dict(
        self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any
    ) -> None:
        """Take the grid shapes of the checkpoint first: upsampling changes them during training."""
        for name in ("density", "color", "color_view"):
            stored = state_dict.get(prefix + name)
            current = getattr(self, name)
            if stored is not None and current is not None and stored.shape != current.shape:
                setattr(self, name, torch.nn.Parameter(current.new_empty(stored.shape)))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """The density grid at `lr`, the colour grids at lr * color_lr_scale."""
        colour = [self.color] if self.color_view is None else [self.color, self.color_view]
        return [
            {"params": [self.density], "lr": lr, "name": "density"},
            {"params": colour, "lr": lr * self.config.color_lr_scale, "name": "color"},
        ]
