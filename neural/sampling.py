"""Where along each ray the radiance field is queried: stratified samples, inverse-CDF resampling, and
samples spaced for contracted (unbounded) space."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from neural.occupancy import PackedSamples, ray_box_intersection

#: Added to every weight before normalising, so a ray with all-zero weights samples uniformly.
PDF_WEIGHT_FLOOR = 1e-5


def stratified_samples(
    near: float,
    far: float,
    num_rays: int,
    num_samples: int,
    perturb: bool,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """t_i = near + (i + u_i) (far - near) / S, u_i ~ U[0,1) if perturb else 1/2; sorted, shape (R,S)."""
    edges = torch.linspace(near, far, num_samples + 1, device=device)
    lower, upper = edges[:-1], edges[1:]
    if perturb:
        jitter = torch.rand((num_rays, num_samples), generator=generator, device=device)
    else:
        jitter = torch.full((num_rays, num_samples), 0.5, device=device)
    return lower + (upper - lower) * jitter


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    num_samples: int,
    deterministic: bool,
    generator: torch.Generator | None = None,
) -> Tensor:
    """t = CDF^-1(u) for the piecewise-constant density `weights` (R,S) on `bins` (R,S+1); (R,N) sorted."""
    weights = weights.detach() + PDF_WEIGHT_FLOOR
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[..., :1]), cdf], dim=-1)  # (R,S+1), starts at 0, ends at 1

    num_rays = bins.shape[0]
    if deterministic:
        u = torch.linspace(0.0, 1.0, num_samples, device=bins.device, dtype=bins.dtype)
        u = u.expand(num_rays, num_samples).contiguous()
    else:
        u = torch.rand((num_rays, num_samples), generator=generator, device=bins.device, dtype=bins.dtype)
        u, _ = torch.sort(u, dim=-1)

    upper_index = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    lower_index = upper_index - 1
    cdf_lower, cdf_upper = cdf.gather(-1, lower_index), cdf.gather(-1, upper_index)
    bin_lower, bin_upper = bins.gather(-1, lower_index), bins.gather(-1, upper_index)
    span = cdf_upper - cdf_lower
    fraction = torch.where(span < 1e-12, torch.zeros_like(span), (u - cdf_lower) / span.clamp_min(1e-12))
    samples = bin_lower + fraction * (bin_upper - bin_lower)
    return samples.detach()


def contraction_spacing(t: Tensor, t_enter: Tensor, t_exit: Tensor, shell: float = 1.0) -> Tensor:
    """s(t): t - t_in inside [t_in, t_out]; -g(t_in - t) before, L + g(t - t_out) after, g(x) = w x / (1 + x).

    An increasing map whose steps are distances inside the inner box and disparity steps outside it, scaled
    by the shell's thickness w (mip-NeRF 360's spacing for w = 1), so that equal steps in s are about equal
    steps in contracted space. L = t_out - t_in; all distances in grid units (world / max half-side).
    """
    length = t_exit - t_enter
    before = -shell * (1.0 - 1.0 / (t_enter - t + 1.0).clamp_min(1.0))
    after = length + shell * (1.0 - 1.0 / (t - t_exit + 1.0).clamp_min(1.0))
    return torch.where(t < t_enter, before, torch.where(t > t_exit, after, t - t_enter))


def contraction_spacing_inverse(s: Tensor, t_enter: Tensor, t_exit: Tensor, shell: float = 1.0) -> Tensor:
    """t(s), the inverse of `contraction_spacing` for s in (-w, L + w): g^-1(y) = 1 / (1 - y / w) - 1."""
    length = t_exit - t_enter
    before = t_enter + 1.0 - 1.0 / (1.0 + s / shell).clamp_min(1e-9)
    after = t_exit - 1.0 + 1.0 / (1.0 - (s - length) / shell).clamp_min(1e-9)
    return torch.where(s < 0, before, torch.where(s > length, after, t_enter + s))


class ContractedRays(NamedTuple):
    """Where rays meet the inner box and their spacing coordinate s at near and far; all (R,), grid units.

    t_enter, t_exit: where a ray enters and leaves the box (for a ray that misses it: its closest approach to
    the centre), clamped to [near, far]; s_near, s_far: `contraction_spacing` at near and far.
    """

    t_enter: Tensor
    t_exit: Tensor
    s_near: Tensor
    s_far: Tensor

    def num_steps(self, step: float) -> Tensor:
        """Samples per ray (R,) long: the steps of length `step` in s from s_near to s_far."""
        return ((self.s_far - self.s_near) / step).ceil().long().clamp_min(0)

    def steps_before_exit(self, step: float) -> Tensor:
        """Steps per ray (R,) long that start before the ray leaves the box (s < L = t_exit - t_enter)."""
        before = ((self.t_exit - self.t_enter - self.s_near) / step).ceil().long()
        return torch.minimum(before.clamp_min(0), self.num_steps(step))


def contracted_rays(
    origins: Tensor, directions: Tensor, near: float, far: float, extent: Tensor | None = None,
    shell: float = 1.0,
) -> ContractedRays:
    """The `ContractedRays` of origins (R,3) in grid units around the inner box [-extent, extent] (default:
    the unit cube) along unit directions (R,3), between near and far (grid units)."""
    half = torch.ones(3, device=origins.device, dtype=origins.dtype) if extent is None else extent.to(origins)
    hits = ray_box_intersection(origins, directions, -half, half)
    closest = -(origins * directions).sum(dim=-1)
    missed = hits.t_exit <= hits.t_enter
    t_enter = torch.where(missed, closest, hits.t_enter).clamp(near, far)
    t_exit = torch.where(missed, closest, hits.t_exit).clamp(near, far)
    s_near = contraction_spacing(torch.full_like(t_enter, near), t_enter, t_exit, shell)
    s_far = contraction_spacing(torch.full_like(t_enter, far), t_enter, t_exit, shell)
    return ContractedRays(t_enter, t_exit, s_near, s_far)


def contracted_steps(
    rays: ContractedRays,
    origins: Tensor,
    directions: Tensor,
    ray_indices: Tensor,
    step_index: Tensor,
    step: float,
    jitter: Tensor,
    shell: float = 1.0,
) -> PackedSamples:
    """Sample number `step_index` (N,) of ray `ray_indices` (N,): s = s_near + (i + j) step (j: jitter (R,)),
    standing for the ray length t(s_i + step/2) - t(s_i - step/2) of its bin (the last bin ends at s_far)."""
    lower = rays.s_near[ray_indices] + step_index.to(origins.dtype) * step
    upper = torch.minimum(lower + step, rays.s_far[ray_indices])
    s = lower + (upper - lower) * jitter[ray_indices]
    enter, exit_ = rays.t_enter[ray_indices], rays.t_exit[ray_indices]
    t = contraction_spacing_inverse(s, enter, exit_, shell)
    t_upper = contraction_spacing_inverse(upper, enter, exit_, shell)
    deltas = t_upper - contraction_spacing_inverse(lower, enter, exit_, shell)
    positions = origins[ray_indices] + directions[ray_indices] * t[:, None]
    return PackedSamples(ray_indices, t, deltas, positions)


def contracted_space_samples(
    origins: Tensor,
    directions: Tensor,
    near: float,
    far: float,
    step: float,
    jitter: Tensor | None = None,
    extent: Tensor | None = None,
    shell: float = 1.0,
) -> PackedSamples:
    """Samples at equal steps of `contraction_spacing` between near and far, packed; grid units.

    origins (R,3) in grid units around the inner box [-extent, extent] (default: the unit cube), unit
    directions (R,3); near/far and the returned t and deltas are grid-unit distances; shell: the contracted
    shell's thickness. The spacing switches from uniform to disparity-linear where the ray leaves the box
    (for a ray that misses it: at its closest approach to the centre). A sample sits at
    s_i = s(near) + (i + j) step (j: jitter (R,) in [0,1), else 1/2) and stands for the ray length
    t(s_i + step/2) - t(s_i - step/2) of its bin, so the deltas tile [near, far] exactly.
    """
    rays = contracted_rays(origins, directions, near, far, extent, shell)
    num_steps = rays.num_steps(step)
    if jitter is None:
        jitter = torch.full((origins.shape[0],), 0.5, device=origins.device, dtype=origins.dtype)
    max_steps = int(num_steps.max()) if origins.shape[0] else 0
    ray_indices, step_index = (
        torch.arange(max_steps, device=origins.device)[None, :] < num_steps[:, None]
    ).nonzero(as_tuple=True)
    return contracted_steps(rays, origins, directions, ray_indices, step_index, step, jitter, shell)
