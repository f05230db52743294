"""Stratified samples cover their bins; inverse-CDF sampling reproduces the coarse weights' distribution."""

import torch

from neural.sampling import sample_pdf, stratified_samples


def test_stratified_samples_fall_one_per_bin_and_are_sorted():
    generator = torch.Generator().manual_seed(0)
    t = stratified_samples(2.0, 6.0, num_rays=100, num_samples=8, perturb=True, generator=generator)
    assert t.shape == (100, 8)
    bin_index = torch.floor((t - 2.0) / 0.5)
    torch.testing.assert_close(bin_index, torch.arange(8.0).expand(100, 8))
    assert (t[:, 1:] > t[:, :-1]).all()
    assert t.std(dim=0).min() > 0.1  # actually jittered


def test_unperturbed_stratified_samples_are_bin_centres():
    t = stratified_samples(0.0, 1.0, num_rays=3, num_samples=4, perturb=False)
    torch.testing.assert_close(t, torch.tensor([0.125, 0.375, 0.625, 0.875]).expand(3, 4))


def test_same_generator_seed_gives_same_samples():
    a = stratified_samples(0, 1, 5, 6, True, generator=torch.Generator().manual_seed(3))
    b = stratified_samples(0, 1, 5, 6, True, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a, b)


def test_inverse_cdf_reproduces_a_known_piecewise_constant_distribution():
    bins = torch.linspace(0.0, 4.0, 5).unsqueeze(0)  # bins [0,1), [1,2), [2,3), [3,4)
    weights = torch.tensor([[1.0, 0.0, 3.0, 6.0]])
    samples = sample_pdf(
        bins, weights, 200_000, deterministic=False, generator=torch.Generator().manual_seed(0)
    )
    histogram = torch.histc(samples, bins=4, min=0.0, max=4.0) / samples.numel()
    torch.testing.assert_close(histogram, torch.tensor([0.1, 0.0, 0.3, 0.6]), atol=5e-3, rtol=0)
    # uniform within a bin
    inside = samples[(samples >= 3) & (samples < 4)]
    assert abs(inside.mean().item() - 3.5) < 0.01


def test_deterministic_inverse_cdf_is_sorted_quantiles():
    bins = torch.tensor([[0.0, 1.0, 2.0]])
    weights = torch.tensor([[1.0, 1.0]])
    samples = sample_pdf(bins, weights, 5, deterministic=True)
    torch.testing.assert_close(samples, torch.tensor([[0.0, 0.5, 1.0, 1.5, 2.0]]), atol=1e-4, rtol=0)


def test_all_zero_weights_sample_uniformly_without_nan():
    bins = torch.linspace(0, 1, 11).expand(3, 11)
    samples = sample_pdf(bins, torch.zeros(3, 10), 1000, deterministic=False)
    assert torch.isfinite(samples).all()
    assert abs(samples.mean().item() - 0.5) < 0.05


# ------------------------------------------------------------------------------- contracted (unbounded) space
def test_contracted_space_samples_are_uniform_inside_the_cube_and_disparity_linear_beyond():
    from neural.sampling import contracted_space_samples

    origins = torch.zeros(1, 3)
    directions = torch.tensor([[1.0, 0.0, 0.0]])
    samples = contracted_space_samples(origins, directions, near=0.0, far=1000.0, step=0.05)
    inside = samples.t < 1.0
    torch.testing.assert_close(samples.t[inside], 0.025 + 0.05 * torch.arange(20.0))
    torch.testing.assert_close(samples.deltas[inside], torch.full((20,), 0.05))
    # beyond the cube, equal steps in 1/(t - 1 + 1) = 1/t: disparity-linear, widening with distance
    disparity = 1.0 / samples.t[~inside]
    steps = disparity[:-1] - disparity[1:]
    assert (samples.deltas[~inside][1:] > samples.deltas[~inside][:-1]).all()
    assert samples.t.numel() < 45  # about 1/step samples for the whole unbounded outside
    assert steps.max() < 0.051
    # the bins tile [near, far]
    torch.testing.assert_close(samples.deltas.sum(), torch.tensor(1000.0), rtol=1e-4, atol=0)


def test_sampling_in_contracted_space_reaches_a_far_wall_a_box_march_misses():
    """A ray from the scene's centre towards a wall 500 units away: the sample bins cover the wall."""
    from neural.contraction import contract
    from neural.occupancy import OccupancyGrid
    from neural.sampling import contracted_space_samples

    generator = torch.Generator().manual_seed(2)
    directions = torch.randn(64, 3, generator=generator)
    directions[:, 0] = directions[:, 0].abs() + 3.0  # all towards +x
    directions = directions / directions.norm(dim=-1, keepdim=True)
    origins = torch.rand(64, 3, generator=generator) * 0.4 - 0.2
    wall_t = (500.0 - origins[:, 0]) / directions[:, 0]
    samples = contracted_space_samples(origins, directions, near=0.05, far=5000.0, step=0.02)
    # the bins tile each ray from near: a sample's bin ends at near + the sum of its ray's deltas so far
    ends = torch.cumsum(samples.deltas.double(), 0)
    first = torch.searchsorted(samples.ray_indices, torch.arange(64))
    upper = 0.05 + ends - (ends - samples.deltas.double())[first][samples.ray_indices]
    lower = upper - samples.deltas
    # every ray has exactly one sample whose bin holds the wall, out in the contracted shell
    holds = (lower <= wall_t[samples.ray_indices]) & (wall_t[samples.ray_indices] <= upper)
    assert torch.equal(samples.ray_indices[holds], torch.arange(64))
    at_wall = contract(samples.positions[holds]).abs().amax(dim=-1)
    assert (at_wall > 1.9).all() and (at_wall < 2.0).all()
    # with about 1/step samples per ray beyond the cube, not thousands
    assert torch.bincount(samples.ray_indices).max() < 2.0 / 0.02 + 1.5 * 3**0.5 / 0.02
    # a box march over the inner cube never gets there
    box = OccupancyGrid(-torch.ones(3), torch.ones(3), (8, 8, 8))
    assert box.march(origins, directions, 0.05, 5000.0, 0.02).t.max() < 2.0


def test_samples_around_a_flat_box_with_a_thin_shell_step_evenly_through_the_contracted_grid():
    """Inside the box the samples are `step` apart; beyond it, consecutive samples stay at most `step` apart
    along every grid axis (no voxel of the shell is skipped), out to the far end, with about as many samples
    as steps across the grid."""
    from neural.contraction import InnerBox
    from neural.sampling import contracted_space_samples, contraction_spacing, contraction_spacing_inverse

    box = InnerBox.around((-2.0, -0.5, -0.5), (2.0, 0.5, 0.5), shell=0.25)
    enter, exit_ = torch.tensor([0.5]).double(), torch.tensor([1.5]).double()
    t = torch.tensor([0.1, 0.5, 1.0, 1.5, 7.0, 1e4]).double()
    for shell in (1.0, 0.25):
        s = contraction_spacing(t, enter, exit_, shell)
        torch.testing.assert_close(contraction_spacing_inverse(s, enter, exit_, shell), t)
        assert s.max() < 1.0 + shell and s.min() > -shell
    for direction in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]):
        origins = torch.tensor([[0.1, 0.05, 0.0]])
        directions = torch.tensor([direction])
        scaled = contracted_space_samples(
            box.to_scaled(origins), directions, 0.0, 1e4 / box.scale, 0.01, None, box.extent(), box.shell
        )
        world = origins + directions * (scaled.t * box.scale)[:, None]
        grid = box.contract(world.double())
        gaps = (grid[1:] - grid[:-1]).abs().amax(dim=-1)  # along any grid axis
        inside = box.contracted_norm(grid[1:]) < 1.0
        torch.testing.assert_close(gaps[inside], torch.full_like(gaps[inside], 0.01), rtol=1e-4, atol=1e-6)
        assert gaps.max() < 0.0101
        assert box.contracted_norm(grid[-1:]).item() > 1.2  # reaches the outer shell (1 + w = 1.25)
        assert gaps.numel() < (2.0 * 1.25 + 0.25) / 0.01  # about one sample per step across the grid
