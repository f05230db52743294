"""What a photographed scene shows where its field is empty: the photos' colours as a smooth function of the
ray's direction, for renders of runs that have no known background.

A run on photographs trains on random background colours (nothing may show through, so the field is opaque
wherever the photos see), and the directions no photo saw stay empty. Rendered on black they were holes that
a viewer reads as missing content, and that cost held-out photos most of their error (the sky beside
Herz-Jesus-P8's facade). The environment fills them with the colour the photos show in nearby directions:

c(d) = clip(sum_k a_k Y_k(d), 0, 1), Y_0 = 1, (Y_1, Y_2, Y_3) = (x, y, z) of the unit direction d, the
coefficients a_k (per channel) fitted by least squares to training pixels' colours by their rays' directions.
First degree: a gradient over the sphere (bright above, darker below), which extrapolates to directions no
photo saw without overshooting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

ENVIRONMENT_RAYS = 1 << 17
"""Training rays the environment is fitted to: enough for 4x3 coefficients, fast to solve."""


def direction_basis(directions: Tensor) -> Tensor:
    """(R,4) the basis Y(d) = (1, x, y, z) of the unit directions of `directions` (R,3), any length."""
    unit = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.cat([torch.ones_like(unit[:, :1]), unit], dim=-1)


@dataclass(frozen=True)
class Environment:
    """Colours by direction (scene frame), c(d) = clip(Y(d) a, 0, 1) with coefficients a (4,3)."""

    coefficients: np.ndarray

    def colours(self, directions: Tensor) -> Tensor:
        """(R,3) colours of rays with directions (R,3)."""
        coefficients = torch.as_tensor(self.coefficients, dtype=directions.dtype, device=directions.device)
        return (direction_basis(directions) @ coefficients).clamp(0.0, 1.0)

    def to_list(self) -> list[list[float]]:
        return np.asarray(self.coefficients, dtype=np.float64).tolist()

    @classmethod
    def from_list(cls, values: list[list[float]]) -> Environment:
        coefficients = np.asarray(values, dtype=np.float64)
        if coefficients.shape != (4, 3) or not np.isfinite(coefficients).all():
            raise ValueError(f"an environment has 4x3 finite coefficients, got shape {coefficients.shape}")
        return cls(coefficients)


def fit_environment(directions: Tensor, colours: Tensor) -> Environment:
    """a = argmin sum_r ||Y(d_r) a - c_r||^2 over rays with directions (R,3) and colours (R,3)."""
    basis = direction_basis(directions.double())
    solution = torch.linalg.lstsq(basis.cpu(), colours.double().cpu()).solution
    return Environment(solution.numpy())


Background = Tensor | Environment
"""What a render shows where its rays are not fully absorbed: one colour (3,) or an environment."""


def background_for(background: Background, directions: Tensor) -> Tensor:
    """The background colours of rays with these directions: (3,) as it is, or (R,3) from an environment."""
    return background.colours(directions) if isinstance(background, Environment) else background
