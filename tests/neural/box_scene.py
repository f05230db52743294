"""Tiny analytic scenes for the NeRF tests: three coloured boxes on white, seen from a ring of cameras, and
the same boxes inside a textured sphere far away (an unbounded scene: no white world around it)."""

from __future__ import annotations

import math

import torch

from neural.bounds import Bounds
from neural.models.base import RadianceModel
from neural.occupancy import ray_box_intersection
from neural.rays import generate_rays

# Three coloured boxes (min, max, rgb) on a white background, seen from a ring of cameras.
BOXES = [
    ((-0.6, -0.5, -0.5), (-0.1, 0.5, 0.2), (0.9, 0.1, 0.1)),
    ((0.1, -0.3, -0.5), (0.6, 0.3, 0.5), (0.1, 0.8, 0.2)),
    ((-0.3, -0.6, 0.25), (0.3, -0.1, 0.6), (0.1, 0.2, 0.9)),
]
SCENE = Bounds(near=1.5, far=5.0, scene_box_min=(-1.0, -1.0, -1.0), scene_box_max=(1.0, 1.0, 1.0))
WHITE = torch.ones(3)


def look_at_pose(position: torch.Tensor) -> torch.Tensor:
    """Camera-to-world (OpenGL axes: looks down -z) at `position`, looking at the origin, +z world up."""
    back = position / position.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    pose = torch.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, back, position
    return pose


def render_boxes(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Ground truth: the colour of the first box each ray hits, else white; (R,3)."""
    nearest = torch.full((origins.shape[0],), math.inf)
    colour = WHITE.expand(origins.shape[0], 3).clone()
    for low, high, rgb in BOXES:
        hits = ray_box_intersection(origins, directions, torch.tensor(low), torch.tensor(high))
        hit = (hits.t_exit > hits.t_enter) & (hits.t_enter > 0) & (hits.t_enter < nearest)
        nearest = torch.where(hit, hits.t_enter, nearest)
        colour[hit] = torch.tensor(rgb)
    return colour


def ring_views(
    num_views: int, size: int, half_fov_deg: float = 25.0, offset: float = 0.0, truth=None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays (origins, directions) and true colours (`truth`, default render_boxes) of `num_views` cameras on
    a ring, size x size pixels; offset turns the ring by that fraction of the angle between views."""
    focal = 0.5 * size / math.tan(math.radians(half_fov_deg))
    origins, directions = [], []
    for k in range(num_views):
        angle = 2 * math.pi * (k + offset) / num_views
        position = 3.0 * torch.tensor([math.cos(angle), math.sin(angle), 0.6 if k % 2 else -0.3])
        rays = generate_rays(look_at_pose(position), size, size, focal)
        origins.append(rays.origins)
        directions.append(rays.directions)
    origins, directions = torch.cat(origins), torch.cat(directions)
    return origins, directions, (truth or render_boxes)(origins, directions)


#: The unbounded scene: the boxes inside a textured sphere of this radius around the origin.
SPHERE_RADIUS = 30.0
UNBOUNDED_SCENE = Bounds(
    near=0.2, far=3000.0, scene_box_min=(-3.0, -3.0, -3.0), scene_box_max=(3.0, 3.0, 3.0), unbounded=True
)


def sphere_texture(points: torch.Tensor) -> torch.Tensor:
    """A smooth colour pattern over the directions of points (N,3) from the origin; (N,3) in [0.15, 0.85]."""
    unit = points / points.norm(dim=-1, keepdim=True)
    longitude, latitude = torch.atan2(unit[:, 1], unit[:, 0]), torch.asin(unit[:, 2].clamp(-1, 1))
    return torch.stack(
        [
            0.5 + 0.35 * torch.sin(3 * longitude) * torch.cos(latitude),
            0.5 + 0.35 * torch.cos(2 * latitude),
            0.5 + 0.3 * torch.sin(2 * longitude + latitude),
        ],
        dim=-1,
    )


def render_boxes_in_sphere(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Ground truth of the unbounded scene: the first box hit, else the sphere's texture where the ray
    leaves the sphere (t = -o.d + sqrt((o.d)^2 - |o|^2 + R^2) for rays from inside)."""
    along = (origins * directions).sum(dim=-1)
    t_sphere = -along + torch.sqrt(along**2 - (origins**2).sum(dim=-1) + SPHERE_RADIUS**2)
    colour = render_boxes(origins, directions)
    background = (colour == WHITE).all(dim=-1)
    far_points = origins[background] + directions[background] * t_sphere[background, None]
    colour[background] = sphere_texture(far_points)
    return colour


def psnr(rendered: torch.Tensor, truth: torch.Tensor) -> float:
    return float(-10 * torch.log10(torch.mean((rendered - truth) ** 2)))


def fit(model: RadianceModel, origins, directions, colours, steps: int, batch: int = 1024, lr: float = 0.3):
    """Adam on the photometric loss of random ray batches, as the trainer does (with aux colours)."""
    generator = torch.Generator().manual_seed(0)
    optimizer = torch.optim.Adam(model.param_groups(lr))
    for step in range(steps):
        if model.on_train_step(step):
            optimizer = torch.optim.Adam(model.param_groups(lr))
        index = torch.randint(0, origins.shape[0], (batch,), generator=generator)
        out = model.render_rays(
            origins[index], directions[index], SCENE.near, SCENE.far, WHITE, True, generator
        )
        loss = torch.mean((out.rgb - colours[index]) ** 2)
        for aux in out.aux_rgb:
            loss = loss + torch.mean((aux - colours[index]) ** 2)
        if out.extra_loss is not None:
            loss = loss + out.extra_loss
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
