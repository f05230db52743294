"""Where along each ray the radiance field is queried: stratified samples and inverse-CDF resampling."""

from __future__ import annotations

import torch
from torch import Tensor

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
