"""A tiny analytic scene for the NeRF tests: three coloured boxes on white, seen from a ring of cameras."""

from __future__ import annotations

import math

import torch

from neural.models.base import RadianceModel
from neural.occupancy import ray_box_intersection
from neural.rays import generate_rays
from neural.scene import SceneInfo

# Three coloured boxes (min, max, rgb) on a white background, seen from a ring of cameras.
BOXES = [
    ((-0.6, -0.5, -0.5), (-0.1, 0.5, 0.2), (0.9, 0.1, 0.1)),
    ((0.1, -0.3, -0.5), (0.6, 0.3, 0.5), (0.1, 0.8, 0.2)),
    ((-0.3, -0.6, 0.25), (0.3, -0.1, 0.6), (0.1, 0.2, 0.9)),
]
SCENE = SceneInfo(near=1.5, far=5.0, scene_box_min=(-1.0, -1.0, -1.0), scene_box_max=(1.0, 1.0, 1.0))
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


def ring_views(num_views: int, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays (origins, directions) and true colours of `num_views` cameras on a ring, size x size pixels."""
    focal = 0.5 * size / math.tan(math.radians(25.0))
    origins, directions = [], []
    for k in range(num_views):
        angle = 2 * math.pi * k / num_views
        position = 3.0 * torch.tensor([math.cos(angle), math.sin(angle), 0.6 if k % 2 else -0.3])
        rays = generate_rays(look_at_pose(position), size, size, focal)
        origins.append(rays.origins)
        directions.append(rays.directions)
    origins, directions = torch.cat(origins), torch.cat(directions)
    return origins, directions, render_boxes(origins, directions)


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
