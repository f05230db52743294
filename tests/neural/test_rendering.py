"""Volume rendering against closed forms."""

import math

import torch

from neural.rendering import SampleWeights, packed_depth_loss, packed_weights, volume_render


def test_constant_density_slab_has_opacity_one_minus_exp_sigma_length():
    sigma_value, length, num_samples = 0.7, 2.0, 64
    delta = length / num_samples
    t_vals = (torch.arange(num_samples) * delta + 1.0).unsqueeze(0)
    sigma = torch.full((1, num_samples), sigma_value)
    rgb = torch.full((1, num_samples, 3), 0.25)
    out = volume_render(sigma, rgb, t_vals, background=torch.ones(3), far_delta=delta)
    expected_opacity = 1 - math.exp(-sigma_value * length)
    torch.testing.assert_close(out.opacity, torch.tensor([expected_opacity]))
    torch.testing.assert_close(out.rgb[0], torch.full((3,), 0.25 * expected_opacity + (1 - expected_opacity)))
    torch.testing.assert_close(out.weights.sum(-1), out.opacity)


def test_slab_depth_matches_the_exponential_distribution_mean():
    sigma_value, length, num_samples = 1.5, 4.0, 4000
    delta = length / num_samples
    t_vals = (torch.arange(num_samples, dtype=torch.float64) * delta).unsqueeze(0)
    out = volume_render(
        torch.full((1, num_samples), sigma_value, dtype=torch.float64),
        torch.zeros((1, num_samples, 3), dtype=torch.float64),
        t_vals,
        background=torch.zeros(3, dtype=torch.float64),
        far_delta=delta,
    )
    # integral_0^L t sigma exp(-sigma t) dt
    s, L = sigma_value, length
    expected = (1 - math.exp(-s * L) * (1 + s * L)) / s
    assert abs(out.depth.item() - expected) < 1e-3


def test_single_opaque_sample_gives_its_colour_and_depth():
    t_vals = torch.tensor([[2.0, 3.0, 4.0, 5.0]])
    sigma = torch.tensor([[0.0, 1e4, 0.0, 0.0]])
    rgb = torch.zeros(1, 4, 3)
    rgb[0, 1] = torch.tensor([0.2, 0.4, 0.6])
    rgb[0, 2] = torch.tensor([1.0, 0.0, 0.0])  # hidden behind the opaque sample
    out = volume_render(sigma, rgb, t_vals, background=torch.ones(3))
    torch.testing.assert_close(out.rgb[0], torch.tensor([0.2, 0.4, 0.6]))
    torch.testing.assert_close(out.depth, torch.tensor([3.0]))
    torch.testing.assert_close(out.opacity, torch.tensor([1.0]))


def test_empty_space_gives_the_background_per_ray():
    t_vals = torch.linspace(2, 6, 16).expand(2, 16)
    background = torch.tensor([[1.0, 1.0, 1.0], [0.1, 0.2, 0.3]])
    out = volume_render(torch.zeros(2, 16), torch.rand(2, 16, 3), t_vals, background=background)
    torch.testing.assert_close(out.rgb, background)
    torch.testing.assert_close(out.opacity, torch.zeros(2))
    torch.testing.assert_close(out.depth, torch.zeros(2))


def test_gradients_flow_to_density_and_colour():
    sigma = torch.full((1, 8), 0.5, requires_grad=True)
    rgb = torch.full((1, 8, 3), 0.5, requires_grad=True)
    out = volume_render(sigma, rgb, torch.linspace(0, 1, 8).unsqueeze(0), torch.ones(3))
    out.rgb.sum().backward()
    assert sigma.grad.abs().sum() > 0 and rgb.grad.abs().sum() > 0


def test_infinite_last_interval_closes_the_ray_without_exceeding_full_opacity():
    # a medium of optical depth 1 in front of the last sample, which the 1e10 interval makes opaque
    t_vals = torch.tensor([[2.0, 3.0, 4.0]])
    sigma = torch.tensor([[0.5, 0.5, 0.3]])
    rgb = torch.tensor([[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])
    out = volume_render(sigma, rgb, t_vals, background=torch.ones(3))
    torch.testing.assert_close(out.opacity, torch.tensor([1.0]))
    behind = math.exp(-1.0)  # transmittance reaching the last sample
    torch.testing.assert_close(out.rgb[0], torch.tensor([1 - behind, 0.0, behind]))
    torch.testing.assert_close(out.weights[0, 2], torch.tensor(behind))


def test_the_depth_loss_pulls_the_termination_depth_to_the_given_depth():
    """One ray through 64 learnable densities, a floater at t = 1 to start with: minimizing the depth loss
    alone moves the termination to D = 3 (within a sample spacing) and empties the ray in front of it."""
    t = torch.linspace(0.5, 4.5, 64, dtype=torch.float64)
    deltas = torch.full_like(t, float(t[1] - t[0]))
    raw = torch.where((t - 1.0).abs() < 0.1, 3.0, -3.0).requires_grad_(True)
    rays = torch.zeros(64, dtype=torch.long)
    optimizer = torch.optim.Adam([raw], lr=0.1)
    target, sigma = torch.tensor([3.0], dtype=torch.float64), torch.tensor([0.05], dtype=torch.float64)

    def termination():
        weights, _ = packed_weights(torch.nn.functional.softplus(raw), deltas, rays, 1)
        return SampleWeights(weights, t, rays)

    before = termination().weights.detach()
    for _ in range(300):
        loss = packed_depth_loss(termination(), 0, target, sigma)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    weights = termination().weights.detach()
    depth = float((weights * t).sum() / weights.sum())
    assert float((before * t).sum() / before.sum()) < 1.5
    assert abs(depth - 3.0) < float(deltas[0])
    assert float(weights[t < 2.5].sum()) < 0.02 * float(weights.sum())


def test_the_depth_loss_counts_only_the_rays_after_first_ray_each_against_its_own_depth():
    t = torch.tensor([1.0, 2.0, 1.0, 2.0, 1.0, 2.0])
    rays = torch.tensor([0, 0, 1, 1, 2, 2])
    weights = torch.tensor([0.9, 0.0, 0.5, 0.5, 0.0, 1.0])
    # rays 1 and 2 against depths 1 and 2, sigma 1: E = (0.5 * 0 + 0.5 * 1) / 1, and 0
    loss = packed_depth_loss(SampleWeights(weights, t, rays), 1, torch.tensor([1.0, 2.0]), torch.ones(2))
    torch.testing.assert_close(loss, torch.tensor((math.log1p(0.5 / (1 + 1e-4)) + 0.0) / 2))
