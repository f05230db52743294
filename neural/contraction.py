"""Unbounded scenes: mip-NeRF 360's contraction of all space into a ball (here: a cube) of radius 2.

A scene's region of interest is the cube of centre c and half-side a (`InnerCube`); unit coordinates
u = (x - c) / a map it onto [-1, 1]^3. The contraction keeps the unit cube as it is and squeezes everything
outside into the shell 1 < ||.|| < 2, so a grid over [-2, 2]^3 holds the whole unbounded scene with its
resolution falling off as 1 / distance^2 (as the pixel footprint of far content does). The norm is the max
norm (as Zip-NeRF and nerfstudio use for grids: the contracted scene fills the cube, no corner is wasted).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

#: The contracted scene lies inside the cube of this half-side.
CONTRACTED_RADIUS = 2.0


def contract(unit_points: Tensor) -> Tensor:
    """contract(u) = u if ||u|| <= 1, else (2 - 1/||u||) u / ||u||, with ||u|| the max norm; (N,3)."""
    norm = unit_points.abs().amax(dim=-1, keepdim=True)
    safe = norm.clamp_min(1.0)  # inside: the scale below is exactly 1
    return unit_points * ((CONTRACTED_RADIUS - 1.0 / safe) / safe)


@dataclass(frozen=True)
class InnerCube:
    """The region of interest of an unbounded scene: the cube of centre `centre` and half-side `half_side`."""

    centre: tuple[float, float, float]
    half_side: float

    @classmethod
    def around(cls, box_min: tuple[float, ...], box_max: tuple[float, ...]) -> InnerCube:
        """The smallest cube with the box's centre that holds the box."""
        centre = tuple(0.5 * (lo + hi) for lo, hi in zip(box_min, box_max, strict=True))
        half = max(0.5 * (hi - lo) for lo, hi in zip(box_min, box_max, strict=True))
        return cls((float(centre[0]), float(centre[1]), float(centre[2])), float(half))

    def to_unit(self, points: Tensor) -> Tensor:
        """u = (x - c) / a."""
        centre = torch.as_tensor(self.centre, dtype=points.dtype, device=points.device)
        return (points - centre) / self.half_side

    def contract(self, points: Tensor) -> Tensor:
        """contract((x - c) / a): world points (N,3) into [-2, 2]^3."""
        return contract(self.to_unit(points))
