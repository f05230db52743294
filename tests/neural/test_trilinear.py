"""Trilinear grid lookups split over threads: grid_sample's values and grid gradient, whatever the split."""

import pytest
import torch
import torch.nn.functional as F

from neural.trilinear import MAX_SPLIT_GRADIENT_BYTES, lookup_parts, trilinear


def grid_sample_reference(grid: torch.Tensor, coordinates: torch.Tensor) -> torch.Tensor:
    """F.grid_sample at points (N,3) in (X,Y,Z) order of a (1,C,X,Y,Z) grid; (N,C)."""
    values = F.grid_sample(grid, coordinates.flip(-1).reshape(1, 1, 1, -1, 3), align_corners=True)
    return values.reshape(grid.shape[1], -1).T


@pytest.fixture
def three_threads():
    """Three torch threads: the points split into three batch entries, the last one padded."""
    previous = torch.get_num_threads()
    torch.set_num_threads(3)
    yield
    torch.set_num_threads(previous)


@pytest.mark.parametrize("channels", [1, 4])
def test_values_and_grid_gradient_equal_grid_samples_inside_and_outside_the_grid(three_threads, channels):
    generator = torch.Generator().manual_seed(0)
    grid = torch.randn((1, channels, 5, 7, 6), generator=generator, requires_grad=True)
    coordinates = torch.rand((101, 3), generator=generator) * 2.2 - 1.1  # some outside: zeros padding
    upstream = torch.randn((101, channels), generator=generator)
    assert lookup_parts(grid) == 3
    values = trilinear(grid, coordinates)
    (gradient,) = torch.autograd.grad((values * upstream).sum(), grid)
    expected = grid_sample_reference(grid, coordinates)
    (expected_gradient,) = torch.autograd.grad((expected * upstream).sum(), grid)
    assert torch.allclose(values, expected, atol=1e-6)
    assert torch.allclose(gradient, expected_gradient, atol=1e-5)
    assert gradient.abs().sum() > 0  # the points reach the grid (the test can fail)


def test_a_lookup_is_split_per_thread_into_no_more_gradient_copies_than_fit_the_budget(three_threads):
    def grid_of(num_values: int) -> torch.Tensor:
        return torch.zeros((1, 1, num_values, 1, 1), requires_grad=True)

    values = MAX_SPLIT_GRADIENT_BYTES // 4 // 3  # float32 values whose 3 gradient copies just fit
    assert lookup_parts(grid_of(values)) == 3
    assert lookup_parts(grid_of(values + 1)) == 2
    assert lookup_parts(grid_of(MAX_SPLIT_GRADIENT_BYTES // 4 + 1)) == 1  # not even one copy fits
    large = grid_of(values + 1)
    with torch.no_grad():  # no backward pass, no gradient copies
        assert lookup_parts(large) == 3
    assert lookup_parts(large.detach()) == 3


def test_no_points_give_no_values_and_a_vertex_gives_its_value():
    grid = torch.randn((1, 2, 3, 3, 3))
    assert trilinear(grid, torch.zeros((0, 3))).shape == (0, 2)
    assert torch.allclose(trilinear(grid, torch.zeros((1, 3))), grid[0, :, 1, 1, 1][None])  # the centre
    assert torch.allclose(trilinear(grid, -torch.ones((1, 3))), grid[0, :, 0, 0, 0][None])  # the first
