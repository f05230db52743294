"""Shared RANSAC helpers: the adaptive iteration count and batched minimal samples."""

from __future__ import annotations

import numpy as np


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float, max_iterations: int) -> int:
    """N = log(1 - p) / log(1 - w^s): samples needed to draw one all-inlier sample with confidence p."""
    all_inlier_probability = inlier_ratio**sample_size
    if all_inlier_probability <= 0.0:
        return max_iterations
    if all_inlier_probability >= 1.0:
        return 1
    needed = np.log(1.0 - confidence) / np.log(1.0 - all_inlier_probability)
    return int(min(max_iterations, max(1, np.ceil(needed))))


def random_samples(rng: np.random.Generator, num_items: int, sample_size: int, batch: int) -> np.ndarray:
    """(batch, sample_size) indices, each row sampled without replacement from range(num_items)."""
    return np.argpartition(rng.random((batch, num_items)), sample_size - 1, axis=1)[:, :sample_size]
