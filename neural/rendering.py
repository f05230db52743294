"""Emission-absorption volume rendering of samples along rays (NeRF eq. 3)."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

#: Added to a ray's opacity in the depth loss, so that an empty ray (no weight) stays finite.
DEPTH_LOSS_EPSILON = 1e-4


class RenderOutput(NamedTuple):
    """Per-ray colour (R,3), expected depth (R,), accumulated opacity (R,) and sample weights (R,S)."""

    rgb: Tensor
    depth: Tensor
    opacity: Tensor
    weights: Tensor


def sample_deltas(t_vals: Tensor, far_delta: float) -> Tensor:
    """delta_i = t_{i+1} - t_i, with the last interval set to far_delta; (R,S)."""
    deltas = t_vals[..., 1:] - t_vals[..., :-1]
    return torch.cat([deltas, torch.full_like(t_vals[..., :1], far_delta)], dim=-1)


def compositing_weights(sigma: Tensor, deltas: Tensor) -> Tensor:
    """w_i = T_i (1 - exp(-sigma_i delta_i)), T_i = exp(-sum_{j<i} sigma_j delta_j); (R,S)."""
    optical_depth = sigma * deltas
    alpha = 1.0 - torch.exp(-optical_depth)
    # Exclusive cumulative sum in log space: exact T_i, no product of many (1 - alpha) factors. Shifted
    # rather than (cumsum - term): that difference cancels catastrophically after a huge far_delta term.
    accumulated = torch.cat(
        [torch.zeros_like(optical_depth[..., :1]), torch.cumsum(optical_depth[..., :-1], dim=-1)], dim=-1
    )
    transmittance = torch.exp(-accumulated)
    return transmittance * alpha


def volume_render(
    sigma: Tensor, rgb: Tensor, t_vals: Tensor, background: Tensor, far_delta: float = 1e10
) -> RenderOutput:
    """C = sum_i T_i (1 - exp(-sigma_i delta_i)) c_i + (1 - opacity) background; depth = sum_i w_i t_i.

    sigma (R,S) >= 0, rgb (R,S,3), t_vals (R,S) sorted distances along unit directions, background (3,) or
    (R,3). Depth is the weight-averaged distance, not normalized by opacity (0 where the ray is empty).
    """
    weights = compositing_weights(sigma, sample_deltas(t_vals, far_delta))
    opacity = weights.sum(dim=-1)
    colour = (weights.unsqueeze(-1) * rgb).sum(dim=-2) + (1.0 - opacity).unsqueeze(-1) * background
    depth = (weights * t_vals).sum(dim=-1)
    return RenderOutput(rgb=colour, depth=depth, opacity=opacity, weights=weights)


class PackedRenderOutput(NamedTuple):
    """Per-ray colour (R,3), depth (R,), opacity (R,); per-sample weights (N,) and transmittance (N,)."""

    rgb: Tensor
    depth: Tensor
    opacity: Tensor
    weights: Tensor
    transmittance: Tensor


def packed_transmittance(optical_depth: Tensor, ray_indices: Tensor, num_rays: int) -> Tensor:
    """T_i = exp(-sum_{j<i, same ray} sigma_j delta_j) for packed samples sorted by ray; (N,)."""
    if optical_depth.numel() == 0:
        return optical_depth.new_ones((0,))
    return torch.exp(-segmented_exclusive_sum(optical_depth, ray_indices, num_rays))


def segmented_exclusive_sum(values: Tensor, ray_indices: Tensor, num_rays: int) -> Tensor:
    """S_i = sum_{j<i, same ray} v_j for packed samples sorted by ray; (N,), in the dtype of values.

    A global cumulative sum minus its value at each ray's first sample, taken in float64 so long packed
    lists keep the precision of a per-ray sum.
    """
    if values.numel() == 0:
        return values.clone()
    cumulative = torch.cumsum(values.double(), dim=0)
    exclusive = cumulative - values.double()
    counts = torch.bincount(ray_indices, minlength=num_rays)
    ray_start = (torch.cumsum(counts, dim=0) - counts).clamp_max(values.numel() - 1)
    return (exclusive - exclusive[ray_start][ray_indices]).to(values.dtype)


def packed_distortion(
    weights: Tensor, t: Tensor, deltas: Tensor, ray_indices: Tensor, num_rays: int
) -> Tensor:
    """Mean over rays of mip-NeRF 360's distortion loss (eq. 15) of packed samples sorted by ray then t.

    L = sum_{i,j} w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 delta_i, in O(N) as
    2 sum_i w_i (t_i W_i - S_i) with W_i = sum_{j<i} w_j and S_i = sum_{j<i} w_j t_j (same ray).
    """
    if weights.numel() == 0:
        return weights.sum()
    before = segmented_exclusive_sum(weights, ray_indices, num_rays)
    weighted_t_before = segmented_exclusive_sum(weights * t, ray_indices, num_rays)
    between = 2.0 * weights * (t * before - weighted_t_before)
    within = weights.square() * deltas / 3.0
    return (between + within).sum() / num_rays


def packed_weights(
    sigma: Tensor, deltas: Tensor, ray_indices: Tensor, num_rays: int
) -> tuple[Tensor, Tensor]:
    """w_i = T_i (1 - exp(-sigma_i delta_i)) and T_i of packed samples sorted by ray; both (N,)."""
    optical_depth = sigma * deltas
    transmittance = packed_transmittance(optical_depth, ray_indices, num_rays)
    return transmittance * -torch.expm1(-optical_depth), transmittance


def composite_packed(
    weights: Tensor, rgb: Tensor, t: Tensor, ray_indices: Tensor, num_rays: int, background: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Per ray: C = sum_i w_i c_i + (1 - O) background, O = sum_i w_i, depth = sum_i w_i t_i."""
    opacity = weights.new_zeros(num_rays).index_add(0, ray_indices, weights)
    colour = rgb.new_zeros((num_rays, 3)).index_add(0, ray_indices, weights[:, None] * rgb)
    colour = colour + (1.0 - opacity)[:, None] * background
    depth = t.new_zeros(num_rays).index_add(0, ray_indices, weights * t)
    return colour, depth, opacity


def volume_render_packed(
    sigma: Tensor,
    rgb: Tensor,
    t: Tensor,
    deltas: Tensor,
    ray_indices: Tensor,
    num_rays: int,
    background: Tensor,
) -> PackedRenderOutput:
    """volume_render of packed samples: C_r = sum_{i in r} T_i (1 - exp(-sigma_i delta_i)) c_i + (1 - O_r) bg.

    sigma (N,), rgb (N,3), t (N,), deltas (N,) and ray_indices (N,) sorted by ray then t; rays without
    samples get the background. Same closed form and conventions as `volume_render`.
    """
    weights, transmittance = packed_weights(sigma, deltas, ray_indices, num_rays)
    colour, depth, opacity = composite_packed(weights, rgb, t, ray_indices, num_rays, background)
    return PackedRenderOutput(colour, depth, opacity, weights, transmittance)


class SampleWeights(NamedTuple):
    """Packed samples of a render, sorted by ray: compositing weight (N,), distance t (N,), ray index (N,)."""

    weights: Tensor
    t: Tensor
    ray_indices: Tensor


def packed_depth_loss(samples: SampleWeights, first_ray: int, depth: Tensor, sigma: Tensor) -> Tensor:
    """Mean over rays r = first_ray + k of log(1 + E_r / sigma_k^2), E_r = sum_i w_i (t_i - D_k)^2 / sum_i w_i

    E_r is the mean squared distance of the ray's termination (the normalized weights) from the known
    depth D_k: it pulls the weight to D_k and empties the ray in front of it and behind it; log(1 + x)
    (Cauchy) keeps a wrong depth from dominating. depth, sigma (K,) of the rays first_ray ... first_ray+K-1.
    """
    count = depth.shape[0]
    mine = samples.ray_indices >= first_ray
    ray = samples.ray_indices[mine] - first_ray
    weights, t = samples.weights[mine], samples.t[mine]
    opacity = weights.new_zeros(count).index_add(0, ray, weights)
    squared = weights.new_zeros(count).index_add(0, ray, weights * (t - depth[ray]).square())
    return torch.log1p(squared / (opacity + DEPTH_LOSS_EPSILON) / sigma.square()).mean()
