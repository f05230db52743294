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
