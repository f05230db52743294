"""Rays follow the OpenGL pinhole convention with pixel centres at +0.5 and unit directions."""

import math

import torch

from neural.rays import generate_rays


def test_centre_pixel_of_identity_camera_looks_down_minus_z():
    rays = generate_rays(torch.eye(4), width=5, height=5, fx=10.0)
    centre = rays.directions.reshape(5, 5, 3)[2, 2]
    torch.testing.assert_close(centre, torch.tensor([0.0, 0.0, -1.0]))
    torch.testing.assert_close(rays.origins, torch.zeros(25, 3))


def test_directions_are_unit_and_row_major_with_y_up():
    rays = generate_rays(torch.eye(4), width=4, height=2, fx=2.0)
    torch.testing.assert_close(rays.directions.norm(dim=-1), torch.ones(8))
    grid = rays.directions.reshape(2, 4, 3)
    # top-left pixel centre (0.5, 0.5) with cx=2, cy=1: x = -1.5/2, y = +0.5/2 (image rows go down, y up)
    expected = torch.tensor([-0.75, 0.25, -1.0])
    torch.testing.assert_close(grid[0, 0], expected / expected.norm())
    assert grid[0, 1, 0] > grid[0, 0, 0] and grid[1, 0, 1] < grid[0, 0, 1]


def test_pose_rotates_directions_and_sets_origin():
    # camera at (1,2,3) turned 90 degrees about +y: its -z axis points along world -x
    angle = math.pi / 2
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    )
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    rays = generate_rays(c2w, width=3, height=3, fx=5.0)
    torch.testing.assert_close(rays.directions[4], torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(rays.origins[0], torch.tensor([1.0, 2.0, 3.0]))


def test_principal_point_and_fy_are_respected():
    rays = generate_rays(torch.eye(4), width=4, height=4, fx=1.0, fy=2.0, cx=0.5, cy=0.5)
    d = rays.directions[0]  # pixel (0,0) centre sits on the principal point
    torch.testing.assert_close(d, torch.tensor([0.0, 0.0, -1.0]))
    d = rays.directions[5]  # pixel (1,1): x = 1/1, y = -1/2
    expected = torch.tensor([1.0, -0.5, -1.0])
    torch.testing.assert_close(d, expected / expected.norm())
