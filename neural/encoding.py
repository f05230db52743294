"""Positional encoding gamma(p) of positions and view directions (NeRF section 5.1)."""

from __future__ import annotations

import torch
from torch import Tensor


class PositionalEncoding(torch.nn.Module):
    """gamma(p) = (p, sin(2^0 p), cos(2^0 p), ..., sin(2^(L-1) p), cos(2^(L-1) p)), per coordinate.

    Frequencies 2^k without the paper's factor pi, as in the authors' released code (which also prepends
    the raw input); the scene's coordinates span a few units, so the lowest band does not wrap around.
    """

    def __init__(self, num_bands: int, input_dim: int = 3, include_input: bool = True) -> None:
        super().__init__()
        self.num_bands = num_bands
        self.input_dim = input_dim
        self.include_input = include_input
        self.register_buffer(
            "frequencies", 2.0 ** torch.arange(num_bands, dtype=torch.float32), persistent=False
        )

    @property
    def output_dim(self) -> int:
        return self.input_dim * (2 * self.num_bands + int(self.include_input))

    def forward(self, x: Tensor) -> Tensor:
        """(..., D) -> (..., D (1 + 2L)) ordered [x, sin(f0 x), cos(f0 x), sin(f1 x), ...]."""
        scaled = x.unsqueeze(-2) * self.frequencies.unsqueeze(-1)  # (..., L, D)
        bands = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2)  # (..., L, 2, D)
        encoded = bands.flatten(start_dim=-3)
        return torch.cat([x, encoded], dim=-1) if self.include_input else encoded
