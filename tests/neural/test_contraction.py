"""mip-NeRF 360's contraction (max norm): identity inside the unit cube, all else into the shell below 2."""

import pytest
import torch

from neural.contraction import InnerBox, contract, uncontracted_norm

CONTRACTED_RADIUS = 2.0  # 1 + w with mip-NeRF 360's shell, w = 1 (contract's default)


def test_points_inside_the_unit_cube_are_unchanged():
    points = torch.rand(1000, 3) * 2 - 1
    torch.testing.assert_close(contract(points), points)


def test_points_outside_land_in_the_shell_between_1_and_2_on_their_own_ray():
    generator = torch.Generator().manual_seed(0)
    directions = torch.randn(500, 3, generator=generator)
    directions = directions / directions.abs().amax(dim=-1, keepdim=True)  # max norm 1
    radii = 1.0 + torch.rand(500, 1, generator=generator) * 1e4
    contracted = contract(directions * radii)
    norms = contracted.abs().amax(dim=-1)
    assert (norms > 1.0).all() and (norms < CONTRACTED_RADIUS).all()
    torch.testing.assert_close(norms, 2.0 - 1.0 / radii[:, 0])  # 2 - 1/||x||
    cosine = torch.nn.functional.cosine_similarity(contracted, directions, dim=-1)
    torch.testing.assert_close(cosine, torch.ones(500))
    assert contract(torch.tensor([[1e30, 0.0, 0.0]]))[0, 0] == CONTRACTED_RADIUS  # infinity maps to 2


def test_contraction_is_continuous_at_the_cube_surface():
    inside, outside = torch.tensor([[1.0 - 1e-6, 0.3, -0.2]]), torch.tensor([[1.0 + 1e-6, 0.3, -0.2]])
    torch.testing.assert_close(contract(inside), contract(outside), atol=1e-5, rtol=0)


def test_contraction_is_monotone_along_rays_from_the_centre_and_keeps_the_order_of_norms():
    generator = torch.Generator().manual_seed(1)
    directions = torch.randn(200, 3, generator=generator)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    t = torch.logspace(-3, 4, 400, dtype=torch.float64)
    points = directions.double()[:, None, :] * t[None, :, None]
    contracted = contract(points.reshape(-1, 3)).reshape(200, 400, 3)
    along = (contracted * directions.double()[:, None, :]).sum(dim=-1)  # position along the ray
    assert (along[:, 1:] > along[:, :-1]).all()
    assert (contracted.abs().amax(dim=-1) < CONTRACTED_RADIUS).all()
    # any two points: the farther one (max norm) stays the farther one
    p, q = torch.randn(2, 5000, 3, generator=generator).double() * torch.logspace(-1, 3, 5000)[None, :, None]
    farther = p.abs().amax(dim=-1) < q.abs().amax(dim=-1)
    assert torch.equal(farther, contract(p).abs().amax(dim=-1) < contract(q).abs().amax(dim=-1))


def test_inner_cube_holds_its_box_and_maps_it_to_the_unit_cube():
    cube = InnerBox.around((-1.0, 0.0, 2.0), (3.0, 1.0, 4.0), cube=True)
    assert cube.centre == (1.0, 0.5, 3.0) and cube.half_sides == (2.0, 2.0, 2.0) and cube.scale == 2.0
    corners = torch.tensor([[-1.0, 0.0, 2.0], [3.0, 1.0, 4.0]])
    torch.testing.assert_close(cube.contract(corners), cube.to_scaled(corners))  # inside: identity
    assert cube.to_scaled(corners).abs().max() <= 1.0


def test_an_inner_box_keeps_world_proportions_inside_and_its_shell_holds_everything_beyond():
    """Grid coordinates are (x - c) / max(h) inside the box: a voxel is as long along every axis."""
    box = InnerBox.around((-2.0, -0.5, 0.0), (2.0, 0.5, 1.0), shell=0.25)
    assert box.half_sides == (2.0, 0.5, 0.5) and box.scale == 2.0
    torch.testing.assert_close(box.extent(), torch.tensor([1.0, 0.25, 0.25]))
    inside = torch.tensor([[-2.0, -0.5, 0.0], [1.0, 0.25, 0.75], [2.0, 0.5, 1.0]])
    torch.testing.assert_close(box.contract(inside), box.to_scaled(inside))
    torch.testing.assert_close(box.contracted_norm(box.contract(inside)), torch.tensor([1.0, 0.5, 1.0]))
    generator = torch.Generator().manual_seed(3)
    far = torch.randn(2000, 3, generator=generator).double() * torch.logspace(0, 4, 2000)[:, None]
    contracted = box.contract(far)
    extent = box.contracted_extent.double()
    assert (contracted.abs() <= extent + 1e-9).all()  # the whole world inside (1 + w) h / max(h)
    # going out along +y: 1 + w (1 - 1/r) in unit coordinates, times 0.25 in grid coordinates
    along_y = box.contract(torch.tensor([[0.0, 0.5 + 0.5 * 3.0, 0.5]]).double())  # r = 4
    torch.testing.assert_close(along_y[0, 1], torch.tensor(0.25 * (1.0 + 0.25 * 0.75)).double())


def test_uncontracted_norm_inverts_the_shell_and_stops_at_its_cap():
    generator = torch.Generator().manual_seed(4)
    radii = 1.0 + torch.rand(500, generator=generator).double() * 100.0
    for shell in (1.0, 0.25):
        rho = contract(torch.stack([radii, 0 * radii, 0 * radii], dim=-1), shell)[:, 0]
        torch.testing.assert_close(uncontracted_norm(rho, shell), radii)
    assert uncontracted_norm(torch.tensor([1.25]), 0.25, cap=50.0).item() == pytest.approx(50.0)
    assert uncontracted_norm(torch.tensor([0.5]), 0.25).item() == 0.5
