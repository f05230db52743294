"""The NeRF paper's model: two 8x256 ReLU MLPs (coarse and fine) with hierarchical sampling.

Collapse prevention (the paper's ReLU density can settle on an empty, all-background scene at the start
of training on white-background data, after which the ReLU units are dead and never recover): the trainer
samples rays from the central crop of each image for the first steps (`TrainConfig.precrop_steps`, the
authors' own remedy for the Blender scenes), and this model adds Gaussian noise to the raw density before
the ReLU during training (`raw_noise_std`, the paper's regulariser), which keeps a gradient on
pre-activations that are slightly negative. Both only act during training; rendering is the paper's.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from neural.encoding import PositionalEncoding
from neural.models.base import Bounds, RadianceModel, RayBundleOutput
from neural.rendering import RenderOutput, volume_render
from neural.sampling import sample_pdf, stratified_samples


class VanillaModelConfig(BaseModel):
    """Architecture and sampling of the paper's model (defaults = the paper's)."""

    model_config = ConfigDict(extra="forbid")

    depth: int = Field(8, ge=2, description="Linear layers of the position trunk.")
    width: int = Field(256, ge=1, description="Units per trunk layer.")
    skip_after: int = Field(
        5, ge=1, description="Concatenate the encoded position to the activation of this (1-based) layer."
    )
    colour_width: int = Field(128, ge=1, description="Units of the view-dependent colour layer.")
    position_bands: int = Field(10, ge=0, description="Frequency bands of the position encoding.")
    direction_bands: int = Field(4, ge=0, description="Frequency bands of the direction encoding.")
    coarse_samples: int = Field(64, ge=2, description="Stratified samples per ray (coarse network).")
    fine_samples: int = Field(128, ge=0, description="Extra inverse-CDF samples per ray (fine network).")
    raw_noise_std: float = Field(
        0.0,
        ge=0,
        description="Std of Gaussian noise on the raw density during training (the paper: 0 for"
        " synthetic scenes, 1 for real ones).",
    )
    density_bias_init: float | None = Field(
        0.1,
        description="Initial bias of the density output, so that every ReLU density starts alive "
        "(None: PyTorch's default init, as in the paper's code).",
    )
    far_delta: float = Field(1e10, gt=0, description="Length of the last sample interval of each ray.")


class NerfMLP(nn.Module):
    """F(gamma(x), gamma(d)) -> (sigma, rgb): ReLU trunk with one skip, density head, colour branch."""

    def __init__(self, config: VanillaModelConfig) -> None:
        super().__init__()
        self.position_encoding = PositionalEncoding(config.position_bands)
        self.direction_encoding = PositionalEncoding(config.direction_bands)
        position_dim = self.position_encoding.output_dim
        self.skip_after = config.skip_after
        trunk = []
        for index in range(config.depth):
            in_features = position_dim if index == 0 else config.width
            if index == config.skip_after:
                in_features += position_dim
            trunk.append(nn.Linear(in_features, config.width))
        self.trunk = nn.ModuleList(trunk)
        self.density_head = nn.Linear(config.width, 1)
        self.feature_layer = nn.Linear(config.width, config.width)
        self.colour_layer = nn.Linear(config.width + self.direction_encoding.output_dim, config.colour_width)
        self.rgb_head = nn.Linear(config.colour_width, 3)
        # The density output at initialization varies little across points (std ~0.01) around a
        # seed-dependent offset (~+-0.05): a negative offset leaves every ReLU density at zero with no
        # gradient, an empty scene that never recovers. A positive bias starts every density alive.
        if config.density_bias_init is not None:
            nn.init.constant_(self.density_head.bias, config.density_bias_init)

    def forward(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """points (R,S,3), unit directions (R,3) -> raw density (R,S) before the ReLU, rgb (R,S,3)."""
        encoded_points = self.position_encoding(points)
        h = encoded_points
        for index, layer in enumerate(self.trunk):
            if index == self.skip_after:
                h = torch.cat([encoded_points, h], dim=-1)
            h = torch.relu(layer(h))
        raw_density = self.density_head(h).squeeze(-1)
        encoded_directions = self.direction_encoding(directions).unsqueeze(-2).expand(*h.shape[:-1], -1)
        features = self.feature_layer(h)
        colour = torch.relu(self.colour_layer(torch.cat([features, encoded_directions], dim=-1)))
        return raw_density, torch.sigmoid(self.rgb_head(colour))


class VanillaModel(RadianceModel):
    """Coarse network on stratified samples, fine network on those plus inverse-CDF samples."""

    model_name: ClassVar[str] = "vanilla"
    # The paper: 4096 rays per batch on a GPU, lr 5e-4 decaying 10x over 500k steps (the authors' code),
    # 500 steps of centre crops. 1024 rays keeps a CPU step to seconds.
    train_defaults: ClassVar[dict[str, Any]] = {
        "steps": 200_000,
        "batch_rays": 1024,
        "lr": 5e-4,
        "lr_decay": 0.1,
        "lr_decay_steps": 500_000,
        "precrop_steps": 500,
    }

    def __init__(self, scene: Bounds, config: VanillaModelConfig | None = None) -> None:
        super().__init__(scene)
        self.config = config or VanillaModelConfig()
        self.coarse = NerfMLP(self.config)
        self.fine = NerfMLP(self.config) if self.config.fine_samples > 0 else None

    def _render_samples(
        self,
        network: NerfMLP,
        origins: Tensor,
        directions: Tensor,
        t_vals: Tensor,
        background: Tensor,
        train: bool,
        generator: torch.Generator | None,
    ) -> RenderOutput:
        points = origins.unsqueeze(-2) + directions.unsqueeze(-2) * t_vals.unsqueeze(-1)
        raw_density, rgb = network(points, directions)
        if train and self.config.raw_noise_std > 0:
            noise = torch.randn(raw_density.shape, generator=generator, device=raw_density.device)
            raw_density = raw_density + self.config.raw_noise_std * noise
        return volume_render(torch.relu(raw_density), rgb, t_vals, background, self.config.far_delta)

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
        num_rays = origins.shape[0]
        t_coarse = stratified_samples(
            near,
            far,
            num_rays,
            self.config.coarse_samples,
            perturb=train,
            generator=generator,
            device=origins.device,
        )
        coarse = self._render_samples(
            self.coarse, origins, directions, t_coarse, background, train, generator
        )
        if self.fine is None:
            return RayBundleOutput(rgb=coarse.rgb, depth=coarse.depth, opacity=coarse.opacity)
        midpoints = 0.5 * (t_coarse[:, 1:] + t_coarse[:, :-1])
        bins = torch.cat(
            [torch.full_like(t_coarse[:, :1], near), midpoints, torch.full_like(t_coarse[:, :1], far)], dim=-1
        )
        t_importance = sample_pdf(
            bins, coarse.weights, self.config.fine_samples, deterministic=not train, generator=generator
        )
        t_fine, _ = torch.sort(torch.cat([t_coarse, t_importance], dim=-1), dim=-1)
        fine = self._render_samples(self.fine, origins, directions, t_fine, background, train, generator)
        return RayBundleOutput(rgb=fine.rgb, depth=fine.depth, opacity=fine.opacity, aux_rgb=[coarse.rgb])
