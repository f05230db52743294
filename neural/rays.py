"""Camera rays from pinhole intrinsics and camera-to-world poses.

Convention: poses are camera-to-world 4x4 matrices in OpenGL camera axes (x right, y up, the camera looks
down its -z axis); pixel (column u, row v) has its centre at (u + 0.5, v + 0.5). Ray directions are unit
vectors, so a sample's ray parameter t is its Euclidean distance from the camera centre.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class Rays(NamedTuple):
    """A bundle of rays: origins (R,3) and unit directions (R,3), world frame."""

    origins: Tensor
    directions: Tensor


def camera_directions(pixel_u: Tensor, pixel_v: Tensor, fx: float, fy: float, cx: float, cy: float) -> Tensor:
    """d_cam = normalize(((u + 0.5 - cx) / fx, -(v + 0.5 - cy) / fy, -1)) in OpenGL camera axes; (R,3)."""
    x = (pixel_u + 0.5 - cx) / fx
    y = -(pixel_v + 0.5 - cy) / fy
    z = -torch.ones_like(x)
    directions = torch.stack([x, y, z], dim=-1)
    return directions / directions.norm(dim=-1, keepdim=True)


def pixel_rays(
    c2w: Tensor, pixel_u: Tensor, pixel_v: Tensor, fx: float, fy: float, cx: float, cy: float
) -> Rays:
    """Rays through pixels (u, v): o = c2w[:3,3], d = c2w[:3,:3] d_cam; c2w is (4,4) or per ray (R,4,4)."""
    directions_cam = camera_directions(pixel_u.to(c2w.dtype), pixel_v.to(c2w.dtype), fx, fy, cx, cy)
    rotation = c2w[..., :3, :3]
    if c2w.dim() == 2:
        directions = directions_cam @ rotation.T
        origins = c2w[:3, 3].expand_as(directions)
    else:
        directions = torch.einsum("rij,rj->ri", rotation, directions_cam)
        origins = c2w[:, :3, 3]
    # Renormalize: a pose with slight numerical non-orthogonality would otherwise skew t.
    directions = directions / directions.norm(dim=-1, keepdim=True)
    return Rays(origins.contiguous(), directions)


def generate_rays(
    c2w: Tensor,
    width: int,
    height: int,
    fx: float,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
) -> Rays:
    """All H*W rays of a camera, row-major (index v * W + u); fy defaults to fx, (cx, cy) to the centre."""
    fy = fx if fy is None else fy
    cx = width / 2.0 if cx is None else cx
    cy = height / 2.0 if cy is None else cy
    v, u = torch.meshgrid(
        torch.arange(height, device=c2w.device, dtype=c2w.dtype),
        torch.arange(width, device=c2w.device, dtype=c2w.dtype),
        indexing="ij",
    )
    return pixel_rays(c2w, u.reshape(-1), v.reshape(-1), fx, fy, cx, cy)
