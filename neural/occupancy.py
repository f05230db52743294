"""Empty-space skipping: an occupancy grid learned from the model's own density, and ray marching through it.

The grid covers an axis-aligned box with `resolution` cells per axis. A cell is occupied when the density
inside it may make a sample's opacity exceed a threshold. It starts fully occupied (warm-up) and is then
recomputed from the model's density during training, so it is learned from the images alone (no masks).
A cell may be emptied only once training has evaluated the density of samples in it on enough steps
(`seen_steps`; samples behind an opaque surface count: their density is evaluated for early ray termination):
a cell that no training ray has yet reached keeps its chance to become dense.
Samples are taken at a fixed spacing along each ray inside the box and kept only in occupied cells; the
result is *packed*: one flat list of samples, sorted by ray and then by distance.

The grid is a density estimator shared by every model (as nerfacc's): a model hands it a density callback
`sigma(x)` of world points, to `update` the cells from and to drop occluded samples in `sample`, and renders
the samples with `render_packed_samples`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from neural.rendering import composite_packed, packed_transmittance, packed_weights

#: sigma(x) >= 0 at world points (N,3) -> (N,).
DensityFn = Callable[[Tensor], Tensor]
#: c(x, d) in [0,1] at world points (N,3) seen along unit directions (N,3) -> (N,3).
ColorFn = Callable[[Tensor, Tensor], Tensor]
#: Points per density-callback call when the grid is updated (bounds the memory of an update).
UPDATE_CHUNK = 2**18
#: Cells per side of the blocks that the first level of ray marching strides through.
COARSE_FACTOR = 4
#: Early ray termination looks the density up at this many first samples of every ray, then only on the rays
#: still visible behind them (a photo's rays mostly end at a surface early; those behind it cost nothing).
TERMINATION_FIRST_SAMPLES = 32


class RayBoxHits(NamedTuple):
    """Entry and exit distances (R,) of rays o + t d through a box; t_exit <= t_enter where a ray misses."""

    t_enter: Tensor
    t_exit: Tensor


class PackedSamples(NamedTuple):
    """Samples of many rays in one flat list, sorted by ray then distance.

    ray_indices (N,) long: the ray of each sample; t (N,): distance along the ray (unit directions);
    deltas (N,): the length of ray each sample stands for; positions (N,3) world points.
    """

    ray_indices: Tensor
    t: Tensor
    deltas: Tensor
    positions: Tensor


def ray_box_intersection(origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor) -> RayBoxHits:
    """Slab test: t_enter = max_k min(t0_k, t1_k), t_exit = min_k max(t0_k, t1_k), t_k = (b_k - o_k) / d_k."""
    # A zero direction component gives +-inf slabs, which min/max handle; avoid 0/0 with a tiny epsilon.
    safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (box_min - origins) / safe
    t1 = (box_max - origins) / safe
    t_enter = torch.minimum(t0, t1).amax(dim=-1)
    t_exit = torch.maximum(t0, t1).amin(dim=-1)
    return RayBoxHits(t_enter, t_exit)


class GridSchedule:
    """Training schedule of a grid model (fast, tensorf): its config names `upsample_steps`,
    `occupancy_warmup_steps` and `occupancy_update_every`; the model has `_upsample(stage)` and
    `update_occupancy()`."""

    def on_train_step(self, step: int) -> bool:
        """Upsample/refit the grids when scheduled (then True: parameters replaced); update the occupancy."""
        replaced = False
        if step in self.config.upsample_steps:
            self._upsample(self.config.upsample_steps.index(step) + 1)
            replaced = True
        if step >= self.config.occupancy_warmup_steps and (
            replaced or step % self.config.occupancy_update_every == 0
        ):
            self.update_occupancy()
        return replaced


class OccupancyGrid(torch.nn.Module):
    """A boolean grid of cells over [box_min, box_max]; all cells start occupied.

    Buffers (saved in state_dict): `occupied` (X,Y,Z) bool, `seen_steps` (X,Y,Z) int32 (training steps that
    evaluated the density of a sample in the cell, see `mark_seen`), `box_min` (3,), `box_max` (3,).
    """

    def __init__(self, box_min: Tensor, box_max: Tensor, resolution: tuple[int, int, int]) -> None:
        super().__init__()
        shape = tuple(int(r) for r in resolution)
        self.register_buffer("box_min", torch.as_tensor(box_min, dtype=torch.float32).clone())
        self.register_buffer("box_max", torch.as_tensor(box_max, dtype=torch.float32).clone())
        self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool))
        self.register_buffer("seen_steps", torch.zeros(shape, dtype=torch.int32))
        self._coarse: Tensor | None = None

    def _load_from_state_dict(
        self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any
    ) -> None:
        """Take the resolution of the checkpoint (the grid is resized during training)."""
        stored = state_dict.get(prefix + "occupied")
        if stored is not None and stored.shape != self.occupied.shape:
            self.occupied = torch.ones(stored.shape, dtype=torch.bool, device=self.occupied.device)
            self.seen_steps = torch.zeros(stored.shape, dtype=torch.int32, device=self.occupied.device)
        self._coarse = None
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @staticmethod
    def upgrade_state(state: dict[str, Tensor], prefix: str) -> None:
        """A checkpoint from before `seen_steps` existed counts every cell as seen (its grid was updated
        without that rule); see neural.checkpoints.load_model_state."""
        occupied = state.get(prefix + "occupied")
        if occupied is not None and prefix + "seen_steps" not in state:
            state[prefix + "seen_steps"] = torch.full(occupied.shape, 2**30, dtype=torch.int32)

    @property
    def resolution(self) -> tuple[int, int, int]:
        x, y, z = self.occupied.shape
        return int(x), int(y), int(z)

    def reset(self, box_min: Tensor, box_max: Tensor, resolution: tuple[int, int, int]) -> None:
        """Move the grid to a new box and resolution, all cells occupied; a new cell keeps the seen count of
        the old cell at its centre (0 outside the old box)."""
        device = self.occupied.device
        box_min = torch.as_tensor(box_min, dtype=torch.float32, device=device).clone()
        box_max = torch.as_tensor(box_max, dtype=torch.float32, device=device).clone()
        shape = tuple(int(r) for r in resolution)
        axes = [
            low + (torch.arange(n, device=device) + 0.5) * (high - low) / n
            for low, high, n in zip(box_min, box_max, shape, strict=True)
        ]
        centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        cell, inside = _cell_indices(self.seen_steps.shape, centres, self.box_min, self.box_max)
        seen = torch.where(inside, self.seen_steps.reshape(-1)[cell], 0).reshape(shape)
        self.box_min, self.box_max = box_min, box_max
        self.occupied = torch.ones(shape, dtype=torch.bool, device=device)
        self.seen_steps = seen.to(torch.int32)
        self._coarse = None

    @torch.no_grad()
    def mark_seen(self, positions: Tensor) -> None:
        """One more seen step for every cell holding one of this training step's samples (N,3)."""
        cell, inside = _cell_indices(self.seen_steps.shape, positions, self.box_min, self.box_max)
        self._mark_cells(cell[inside])

    def _mark_cells(self, cells: Tensor) -> None:
        """One more seen step for each cell (flat indices, repeats counted once)."""
        hit = torch.zeros(self.seen_steps.numel(), dtype=torch.bool, device=cells.device)
        hit[cells] = True
        self.seen_steps += hit.reshape(self.seen_steps.shape)

    def set_occupied(self, occupied: Tensor) -> None:
        """Replace the cell states by `occupied` (same resolution)."""
        if tuple(occupied.shape) != self.resolution:
            raise ValueError(f"occupancy of shape {tuple(occupied.shape)} for a grid of {self.resolution}")
        self.occupied = occupied.to(device=self.occupied.device, dtype=torch.bool)
        self._coarse = None

    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())

    def occupied_box(self) -> tuple[Tensor, Tensor] | None:
        """The world-space bounding box (min, max) of all occupied cells, or None when none is occupied."""
        cells = self.occupied.nonzero()
        if cells.numel() == 0:
            return None
        cell_size = (self.box_max - self.box_min) / torch.tensor(self.resolution, device=cells.device)
        low = self.box_min + cells.amin(dim=0).float() * cell_size
        high = self.box_min + (cells.amax(dim=0).float() + 1.0) * cell_size
        return low, high

    @torch.no_grad()
    def vertex_density(self, density_fn: DensityFn) -> Tensor:
        """sigma at the (X+1, Y+1, Z+1) vertices of the cells, from a density callback."""
        lattice = [n + 1 for n in self.resolution]
        axes = [
            torch.linspace(float(low), float(high), n, device=self.box_min.device)
            for low, high, n in zip(self.box_min, self.box_max, lattice, strict=True)
        ]
        vertices = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        return torch.cat([density_fn(chunk) for chunk in vertices.split(UPDATE_CHUNK)]).reshape(lattice)

    @torch.no_grad()
    def update(
        self,
        density: Tensor | DensityFn,
        step_size: float | Tensor,
        alpha_threshold: float,
        dilation: int = 0,
        min_seen_steps: int = 0,
    ) -> Tensor:
        """Occupied iff the cell's opacity bound exceeds alpha_threshold, dilated by `dilation` cells, or
        training has rendered samples in it on fewer than `min_seen_steps` steps (`mark_seen`).

        density: sigma at the cell vertices (X+1, Y+1, Z+1), or a callback sigma(x) evaluated there. The
        max over a cell's vertices bounds sigma everywhere inside it whenever sigma is a monotonic function
        of a field that is multilinear in the cell (a trilinearly interpolated grid, or a VM factorization,
        on the cells' lattice): then no skipped sample can reach the threshold. For other fields the vertex
        values are a sampled estimate; dilate to be safe. Returns the per-cell bound (see cell_alpha_bound).
        """
        vertex_sigma = density if isinstance(density, Tensor) else self.vertex_density(density)
        alpha = cell_alpha_bound(vertex_sigma, step_size)
        occupied = (alpha > alpha_threshold).float()[None, None]
        if dilation > 0:
            occupied = F.max_pool3d(occupied, kernel_size=2 * dilation + 1, stride=1, padding=dilation)
        self.set_occupied((occupied[0, 0] > 0) | (self.seen_steps < min_seen_steps))
        return alpha

    def query(self, positions: Tensor, mark_seen: bool = False) -> Tensor:
        """Occupied (N,) bool for world points (N,3); points outside the box are never occupied.

        mark_seen: the occupied cells among them count one more seen step (`mark_seen`), in the same lookup.
        """
        if not mark_seen:
            return _lookup(self.occupied, positions, self.box_min, self.box_max, inside_only=True)
        cell, inside = _cell_indices(self.occupied.shape, positions, self.box_min, self.box_max)
        occupied = self.occupied.reshape(-1)[cell] & inside
        with torch.no_grad():
            self._mark_cells(cell[occupied])
        return occupied

    def coarse_occupied(self) -> Tensor:
        """Occupancy of blocks of f^3 cells (f = COARSE_FACTOR) dilated by a block; (X,Y,Z)/f rounded up."""
        if self._coarse is None or self._coarse.device != self.occupied.device:
            f = COARSE_FACTOR
            x, y, z = self.resolution
            padded = F.pad(self.occupied[None, None].float(), (0, -z % f, 0, -y % f, 0, -x % f))
            blocks = F.max_pool3d(padded, kernel_size=f, stride=f)
            self._coarse = F.max_pool3d(blocks, kernel_size=3, stride=1, padding=1)[0, 0] > 0
        return self._coarse

    def steps_per_block(self, step_size: float) -> int:
        """Sample steps in one stride of a two-level march: fewer than a block of COARSE_FACTOR cells, so
        that the samples of a stride lie within one block of its start."""
        cell_size = (self.box_max - self.box_min) / torch.tensor(self.resolution, device=self.box_min.device)
        return max(1, int(float(cell_size.min()) * COARSE_FACTOR / step_size) - 1)

    def block_may_be_occupied(self, points: Tensor) -> Tensor:
        """(N,) bool: False where every cell within one block (COARSE_FACTOR cells) of the point is empty, so
        the samples of a stride of `steps_per_block` steps from it may be skipped unseen."""
        coarse = self.coarse_occupied()
        cell_size = (self.box_max - self.box_min) / torch.tensor(self.resolution, device=points.device)
        coarse_size = torch.tensor(coarse.shape, device=points.device)
        coarse_box_max = self.box_min + cell_size * COARSE_FACTOR * coarse_size
        return _lookup(coarse, points, self.box_min, coarse_box_max, inside_only=False)

    def march(
        self,
        origins: Tensor,
        directions: Tensor,
        near: float,
        far: float,
        step_size: float,
        jitter: Tensor | None = None,
    ) -> PackedSamples:
        """t_i = t_0 + (i + j) step in occupied cells; t_0 = max(near, t_enter), t_i < min(far, t_exit).

        jitter (R,) in [0,1) shifts each ray's samples (training); None samples at the step centres (j=1/2).
        Two levels: the ray first strides through dilated blocks of COARSE_FACTOR^3 cells, and only inside
        occupied blocks are the samples generated and tested against the cells; the dilation by one block
        and a stride below the block size make this skip exactly what a one-level march would.
        """
        num_rays = origins.shape[0]
        device = origins.device
        hits = ray_box_intersection(origins, directions, self.box_min, self.box_max)
        t_start = hits.t_enter.clamp_min(near)
        t_end = hits.t_exit.clamp_max(far)
        num_steps = ((t_end - t_start) / step_size).ceil().clamp_min(0).long()
        if jitter is None:
            jitter = torch.full((num_rays,), 0.5, device=device)
        steps_per_block = self.steps_per_block(step_size)
        num_blocks = (num_steps + steps_per_block - 1) // steps_per_block
        max_blocks = int(num_blocks.max()) if num_rays else 0

        # Level 1: one test per block-sized stride.
        block = torch.arange(max_blocks, device=device)
        ray_index, block_index = (block[None, :] < num_blocks[:, None]).nonzero(as_tuple=True)
        block_t = t_start[ray_index] + (block_index * steps_per_block).to(t_start.dtype) * step_size
        block_points = origins[ray_index] + directions[ray_index] * block_t[:, None]
        keep = self.block_may_be_occupied(block_points)
        ray_index, block_index = ray_index[keep], block_index[keep]

        # Level 2: the samples of the occupied blocks, tested cell by cell.
        step_index = block_index[:, None] * steps_per_block + torch.arange(steps_per_block, device=device)
        ray_index = ray_index[:, None].expand_as(step_index)
        t = t_start[ray_index] + (step_index.to(t_start.dtype) + jitter[ray_index]) * step_size
        valid = (step_index < num_steps[ray_index]) & (t < t_end[ray_index])
        ray_index, t = ray_index[valid], t[valid]
        positions = origins[ray_index] + directions[ray_index] * t[:, None]
        keep = _lookup(self.occupied, positions, self.box_min, self.box_max, inside_only=False)
        ray_index, t, positions = ray_index[keep], t[keep], positions[keep]
        return PackedSamples(ray_index, t, torch.full_like(t, step_size), positions)

    def sample(
        self,
        origins: Tensor,
        directions: Tensor,
        near: float,
        far: float,
        step_size: float,
        jitter: Tensor | None,
        density_fn: DensityFn,
        transmittance_threshold: float,
    ) -> PackedSamples:
        """`march`, then early ray termination (`drop_occluded`)."""
        samples = self.march(origins, directions, near, far, step_size, jitter)
        return drop_occluded(samples, origins.shape[0], density_fn, transmittance_threshold)


def drop_occluded(
    samples: PackedSamples,
    num_rays: int,
    density_fn: DensityFn,
    transmittance_threshold: float,
    first_samples: int = TERMINATION_FIRST_SAMPLES,
) -> PackedSamples:
    """Early ray termination: keep the samples whose transmittance (no grad) is above the threshold.

    The density is looked up at the `first_samples` first samples of every ray, then only at the later
    samples of the rays still visible behind them (T_i = T_head exp(-sum of the later optical depths)): the
    same samples are kept as with every lookup, without paying for those behind early surfaces.
    """
    kept, _ = drop_occluded_after(samples, num_rays, density_fn, transmittance_threshold, None, first_samples)
    return kept


def drop_occluded_after(
    samples: PackedSamples,
    num_rays: int,
    density_fn: DensityFn,
    transmittance_threshold: float,
    start_depth: Tensor | None,
    first_samples: int = TERMINATION_FIRST_SAMPLES,
) -> tuple[PackedSamples, Tensor]:
    """`drop_occluded` of samples that lie behind an optical depth start_depth (R,) already on each ray
    (None: 0); also returns each ray's optical depth after them (R,), exact while below -log(threshold).

    A ray's samples may so be generated and terminated in parts, front to back, with the same result.
    """
    with torch.no_grad():
        ray_indices = samples.ray_indices
        ray_depth = torch.zeros(num_rays, dtype=samples.t.dtype, device=samples.t.device)
        if start_depth is not None:
            ray_depth += start_depth
        if transmittance_threshold <= 0 or samples.t.numel() == 0:
            return samples, ray_depth
        counts = torch.bincount(ray_indices, minlength=num_rays)
        ray_start = counts.cumsum(0) - counts
        rank = torch.arange(ray_indices.numel(), device=ray_indices.device) - ray_start[ray_indices]
        head = (rank < first_samples).nonzero(as_tuple=True)[0]
        head_depth = density_fn(samples.positions[head]) * samples.deltas[head]
        transmittance = torch.zeros_like(samples.t)
        transmittance[head] = torch.exp(-ray_depth[ray_indices[head]]) * packed_transmittance(
            head_depth, ray_indices[head], num_rays
        )
        ray_depth.index_add_(0, ray_indices[head], head_depth)
        visible_after = ray_depth < opaque_depth(transmittance_threshold)
        tail = ((rank >= first_samples) & visible_after[ray_indices]).nonzero(as_tuple=True)[0]
        if tail.numel():
            tail_depth = density_fn(samples.positions[tail]) * samples.deltas[tail]
            tail_rays = ray_indices[tail]
            transmittance[tail] = torch.exp(-ray_depth[tail_rays]) * packed_transmittance(
                tail_depth, tail_rays, num_rays
            )
            ray_depth.index_add_(0, tail_rays, tail_depth)
        keep = (transmittance > transmittance_threshold).nonzero(as_tuple=True)[0]
    return PackedSamples(*(field[keep] for field in samples)), ray_depth


def opaque_depth(transmittance_threshold: float) -> float:
    """-log(threshold): the optical depth behind which early ray termination drops samples (inf at 0)."""
    return -math.log(transmittance_threshold) if transmittance_threshold > 0 else math.inf


class PackedRender(NamedTuple):
    """Per ray colour (R,3), depth (R,), opacity (R,); per sample sigma (N,) and weights (N,)."""

    rgb: Tensor
    depth: Tensor
    opacity: Tensor
    sigma: Tensor
    weights: Tensor


def render_packed_samples(
    samples: PackedSamples,
    directions: Tensor,
    density_fn: DensityFn,
    color_fn: ColorFn,
    background: Tensor,
    color_weight_threshold: float,
) -> PackedRender:
    """Volume rendering of packed samples; colour only where the weight exceeds color_weight_threshold.

    Samples below the threshold keep a zero colour: their weight makes them negligible, and skipping them
    saves most colour lookups (behind surfaces and in the thin air in front of them).
    """
    num_rays = directions.shape[0]
    sigma = density_fn(samples.positions)
    weights, _ = packed_weights(sigma, samples.deltas, samples.ray_indices, num_rays)
    visible = (weights.detach() > color_weight_threshold).nonzero(as_tuple=True)[0]
    rgb = sigma.new_zeros((sigma.shape[0], 3)).index_copy(
        0, visible, color_fn(samples.positions[visible], directions[samples.ray_indices[visible]])
    )
    colour, depth, opacity = composite_packed(
        weights, rgb, samples.t, samples.ray_indices, num_rays, background
    )
    return PackedRender(colour, depth, opacity, sigma, weights)


def cell_alpha_bound(vertex_sigma: Tensor, step_size: float | Tensor) -> Tensor:
    """1 - exp(-max sigma over each cell's 8 vertices * step): one sample step's opacity bound; (X,Y,Z).

    step_size: one world length for every cell, or one per cell (X,Y,Z) where the steps differ.
    """
    cell_max = F.max_pool3d(vertex_sigma[None, None], kernel_size=2, stride=1)[0, 0]
    return -torch.expm1(-cell_max * step_size)


def _lookup(grid: Tensor, positions: Tensor, box_min: Tensor, box_max: Tensor, inside_only: bool) -> Tensor:
    """grid[cell(x)] for a boolean (X,Y,Z) grid spanning the box; (N,).

    inside_only: points outside the box are False; otherwise they take the nearest cell (for points known to
    be inside, where rounding at the box faces must not drop them).
    """
    flat, inside = _cell_indices(grid.shape, positions, box_min, box_max)
    occupied = grid.reshape(-1)[flat]
    return occupied & inside if inside_only else occupied


def _cell_indices(
    shape: tuple[int, ...] | torch.Size, positions: Tensor, box_min: Tensor, box_max: Tensor
) -> tuple[Tensor, Tensor]:
    """Flat index (N,) of the cell of each point in an (X,Y,Z) grid over the box (the nearest cell for points
    outside), and whether the point is inside the box (N,) bool."""
    resolution = torch.tensor(tuple(shape), device=positions.device)
    cell = ((positions - box_min) * (resolution / (box_max - box_min))).floor().long()
    clamped = torch.minimum(cell.clamp_min(0), resolution - 1)
    flat = (clamped[:, 0] * shape[1] + clamped[:, 1]) * shape[2] + clamped[:, 2]
    return flat, ((cell >= 0) & (cell < resolution)).all(dim=-1)
