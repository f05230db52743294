"""Unbounded scenes: mip-NeRF 360's contraction of all space into a ball (here: a box) around the region of
interest.

A scene's region of interest is the box of centre c and half-sides h (`InnerBox`); unit coordinates
u = (x - c) / h (per axis) map it onto [-1, 1]^3. The contraction keeps the unit cube as it is and squeezes
everything outside into the shell 1 < ||.|| < 1 + w (w: the shell's thickness, 1 in mip-NeRF 360), so a grid
over [-(1 + w), 1 + w]^3 holds the whole unbounded scene with its resolution falling off as 1 / distance^2 (as
the pixel footprint of far content does). The norm is the max norm (as Zip-NeRF and nerfstudio use for
grids: the contracted scene fills the cube, no corner is wasted).

Grid coordinates are the contracted unit coordinates times h / max(h): inside the box they are world
coordinates over max(h) (a voxel is as long along every axis), so a flat region of interest (a facade and
its square) does not leave most of an enclosing cube's voxels empty, and a thin shell (w < 1) leaves most
voxels to the inner box: a fraction 1 / (1 + w)^3 of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


def contract(unit_points: Tensor, shell: float = 1.0) -> Tensor:
    """contract(u) = u if ||u|| <= 1, else (1 + w (1 - 1/||u||)) u / ||u||, max norm, w = shell; (N,3)."""
    norm = unit_points.abs().amax(dim=-1, keepdim=True)
    safe = norm.clamp_min(1.0)  # inside: the scale below is exactly 1
    return unit_points * ((1.0 + shell * (1.0 - 1.0 / safe)) / safe)


def uncontracted_norm(rho: Tensor, shell: float = 1.0, cap: float = float("inf")) -> Tensor:
    """r = 1 / (1 - (rho - 1) / w): the unit max norm that contracts to rho > 1 (rho itself inside), at most
    `cap`."""
    return torch.where(rho > 1.0, 1.0 / (1.0 - (rho - 1.0) / shell).clamp_min(1.0 / cap), rho)


@dataclass(frozen=True)
class InnerBox:
    """The region of interest of an unbounded scene: centre `centre`, half-sides `half_sides`, and the
    thickness `shell` of the contracted shell around it."""

    centre: tuple[float, float, float]
    half_sides: tuple[float, float, float]
    shell: float = 1.0

    @classmethod
    def around(
        cls, box_min: tuple[float, ...], box_max: tuple[float, ...], cube: bool = False, shell: float = 1.0
    ) -> InnerBox:
        """The box itself, or (cube) the smallest cube with the box's centre that holds it."""
        centre = tuple(float(0.5 * (lo + hi)) for lo, hi in zip(box_min, box_max, strict=True))
        halves = [float(0.5 * (hi - lo)) for lo, hi in zip(box_min, box_max, strict=True)]
        if cube:
            halves = [max(halves)] * 3
        return cls((centre[0], centre[1], centre[2]), (halves[0], halves[1], halves[2]), shell)

    @property
    def scale(self) -> float:
        """World length of one grid-coordinate unit inside the box: the longest half-side."""
        return max(self.half_sides)

    def extent(self, device: torch.device | str | None = None) -> Tensor:
        """(3,) half-sides of the box in grid coordinates, h / max(h) (all 1 for a cube)."""
        return torch.tensor(self.half_sides, device=device) / self.scale

    @property
    def contracted_extent(self) -> Tensor:
        """(3,) half-sides of the whole contracted scene in grid coordinates, (1 + w) h / max(h)."""
        return (1.0 + self.shell) * self.extent()

    def to_scaled(self, points: Tensor) -> Tensor:
        """(x - c) / max(h): world points in grid units, before contraction."""
        centre = torch.as_tensor(self.centre, dtype=points.dtype, device=points.device)
        return (points - centre) / self.scale

    def contract(self, points: Tensor) -> Tensor:
        """World points (N,3) -> grid coordinates contract((x - c) / h) h / max(h)."""
        return self.contract_scaled(self.to_scaled(points))

    def contract_scaled(self, scaled_points: Tensor) -> Tensor:
        """Points in grid units before contraction, (x - c) / max(h) (N,3) -> grid coordinates."""
        extent = self.extent(scaled_points.device).to(scaled_points.dtype)
        return contract(scaled_points / extent, self.shell) * extent

    def contracted_norm(self, grid_points: Tensor) -> Tensor:
        """The max norm rho of grid points (N,3) in contracted unit coordinates (<= 1: inside the box)."""
        return (grid_points / self.extent(grid_points.device).to(grid_points.dtype)).abs().amax(dim=-1)
