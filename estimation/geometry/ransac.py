"""The one RANSAC driver every robust estimator uses (F, E, H, absolute pose, ...).

An estimator supplies its data (arrays with one row per correspondence), a minimal solver, a residual
function and a threshold; the driver draws batches of minimal samples, pre-verifies each hypothesis on a
few random rows, scores the survivors on every row, re-fits each new best model on its inliers (local
optimization, LO-RANSAC, with an optional non-minimal solver) and stops after the adaptive number of
samples N = log(1 - p) / log(1 - w^s).

Models are numpy arrays whose leading axis batches hypotheses: a minimal solver maps samples
(B, s, ...) to (M, ...) models (M may differ from B: none for a degenerate sample, several for solvers
with multiple roots such as the 5-point essential matrix).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError

HYPOTHESES_PER_BATCH = 64
"""Minimal samples drawn (and solved, batched where the solver allows) per round."""
PREVERIFICATION_POINTS = 50
PREVERIFICATION_FRACTION = 0.5
"""A hypothesis is scored on all rows only if its inlier ratio on PREVERIFICATION_POINTS random ones
reaches this fraction of the best full inlier ratio so far (a cheap T(d,d)-style test)."""

MinimalSolver = Callable[..., np.ndarray]
"""(sample arrays (B, s, ...) of each data array) -> models (M, ...)."""
ResidualFunction = Callable[..., np.ndarray]
"""(models (M, ...), data arrays (N, ...)) -> residuals (M, N); NaN counts as an outlier."""
RefitSolver = Callable[..., np.ndarray]
"""(inlier data arrays (n, ...)) -> models (M, ...): a non-minimal (e.g. least-squares) fit."""


def msac_cost(residuals: np.ndarray, threshold: float) -> np.ndarray:
    """sum_i min(r_i^2, t^2) over the last axis (MSAC, Torr & Zisserman 2000): inliers by how well they fit,
    each outlier at the threshold's cost."""
    return np.minimum(residuals**2, threshold**2).sum(axis=-1)


class RansacResult(NamedTuple):
    """The model with the largest consensus, its inliers and every row's residual under it."""

    model: np.ndarray
    inlier_mask: np.ndarray        # (N,) bool: residual < threshold
    residuals: np.ndarray          # (N,)
    iterations: int                # minimal samples drawn


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


def locally_optimized(model: np.ndarray, model_residuals: np.ndarray, data: Sequence[np.ndarray],
                      residuals: ResidualFunction, threshold: float, refit: RefitSolver | None, refits: int
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """LO: re-fit the model (residuals `model_residuals`) on its inliers up to `refits` times, kept while
    the consensus does not shrink (stops when it no longer changes). Returns (model, its residuals, inlier
    count)."""
    mask = model_residuals < threshold
    count = int(mask.sum())
    for _ in range(refits if refit is not None else 0):
        try:
            candidates = refit(*(array.compress(mask, axis=0) for array in data))
        except DegenerateConfigurationError:
            break
        if len(candidates) == 0:
            break
        candidate_residuals = residuals(candidates, *data)
        masks = candidate_residuals < threshold
        counts = masks.sum(axis=1)
        best = int(counts.argmax())
        if counts[best] < count:
            break
        converged = np.array_equal(masks[best], mask)
        model, model_residuals = candidates[best], candidate_residuals[best]
        mask, count = masks[best], int(counts[best])
        if converged:
            break
    return model, model_residuals, count


def ransac(
    data: Sequence[np.ndarray],
    minimal_solver: MinimalSolver,
    sample_size: int,
    residuals: ResidualFunction,
    threshold: float,
    config: RansacConfig,
    refit: RefitSolver | None = None,
    model_name: str = "model",
) -> RansacResult:
    """argmax_model #{i : residual_i(model) < threshold} over minimal-sample hypotheses, LO-refined.

    `config` gives the confidence, min/max number of samples, the seed and the number of local
    refits; `refit` (optional) re-fits a model on all inliers of each new best hypothesis, kept while
    the consensus does not shrink. DegenerateConfigurationError when there are fewer rows than
    `sample_size` or no model has `sample_size` inliers.
    """
    data = [np.asarray(array) for array in data]
    num = len(data[0])
    if num < sample_size:
        raise DegenerateConfigurationError(
            f"a {model_name} needs at least {sample_size} correspondences, got {num}"
        )
    rng = np.random.default_rng(config.seed)

    def score(models: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every model's residuals (M, N) and inlier count (M,)."""
        model_residuals = residuals(models, *data)
        return model_residuals, (model_residuals < threshold).sum(axis=1)

    best_model, best_residuals, best_count = None, None, -1
    needed, iterations = config.max_iterations, 0
    while iterations < max(needed, config.min_iterations) and iterations < config.max_iterations:
        samples = random_samples(rng, num, sample_size, HYPOTHESES_PER_BATCH)
        iterations += HYPOTHESES_PER_BATCH
        # take / compress pick the same rows as fancy / boolean indexing at a third of the cost.
        models = minimal_solver(*(array.take(samples, axis=0) for array in data))
        if len(models) == 0:
            continue
        if num > PREVERIFICATION_POINTS:
            # Pre-verification: only hypotheses doing well on a random subset are scored on every row
            # (with no more rows than the subset, scoring every row costs the same, so no subset).
            subset = rng.choice(num, size=PREVERIFICATION_POINTS, replace=False)
            subset_ratio = (residuals(models, *(array.take(subset, axis=0) for array in data))
                            < threshold).mean(axis=1)
            passing = subset_ratio >= PREVERIFICATION_FRACTION * max(best_count, 0) / num
            models = models.compress(passing, axis=0)
            if len(models) == 0:
                continue
        scored, counts = score(models)
        best = int(counts.argmax())
        if counts[best] > best_count:
            best_model, best_residuals, best_count = locally_optimized(
                models[best], scored[best], data, residuals, threshold, refit, config.local_refits)
            needed = required_iterations(best_count / num, sample_size, config.confidence,
                                         config.max_iterations)
    if best_model is None or best_count < sample_size:
        raise DegenerateConfigurationError(f"RANSAC found no {model_name} with {sample_size}+ inliers "
                                           f"among {num} correspondences")
    return RansacResult(model=best_model, inlier_mask=best_residuals < threshold,
                        residuals=best_residuals, iterations=iterations)
