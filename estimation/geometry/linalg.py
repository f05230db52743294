"""Small linear-algebra helpers shared by the geometric solvers."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.linalg import _umath_linalg

LM_MAX_ITERATIONS = 100
"""Most iterations of `levenberg_marquardt` (its tolerances stop a converging problem long before)."""
LM_INITIAL_DAMPING = 1e-3
"""Starting lambda of `levenberg_marquardt` (near Gauss-Newton; raised at once if a step fails)."""
LM_DIAGONAL_FLOOR = 1e-12
"""Smallest diagonal entry of J^T J that `levenberg_marquardt`'s damping scales."""


# The two-view solvers call LAPACK on tiny matrices ~14,000 times per lego run, where numpy.linalg's wrappers
# (type checks, an errstate context, result wrapping) cost 2-27 us a call beside the decomposition itself:
# these call the same gufuncs directly (bitwise the same results) for float64 input. Where LAPACK fails
# (NaN input, no convergence) the result is NaN, with numpy's RuntimeWarning, instead of a LinAlgError.


def svd(a: np.ndarray, full_matrices: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """a = U diag(s) V^T for stacked a (..., m, n): (U, s, V^T), s descending, as np.linalg.svd."""
    return (_umath_linalg.svd_f if full_matrices else _umath_linalg.svd_s)(a, signature="d->ddd")


def eigh(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """a = V diag(w) V^T for stacked symmetric a (its lower triangle): (w ascending, V), as np.linalg.eigh."""
    return _umath_linalg.eigh_lo(a, signature="d->dd")


def eigvals(a: np.ndarray) -> np.ndarray:
    """The complex w with det(a - w I) = 0 of stacked square a (..., n, n) -> (..., n)."""
    return _umath_linalg.eigvals(a, signature="d->D")


def inv(a: np.ndarray) -> np.ndarray:
    """a^-1 for stacked square a."""
    return _umath_linalg.inv(a, signature="d->d")


def complete_q(a: np.ndarray) -> np.ndarray:
    """Q (..., m, m) of a = Q R for stacked a (..., m, n) with m > n, as np.linalg.qr(a, "complete")[0]."""
    reflectors = np.array(a, float)            # LAPACK's QR overwrites its input with the reflectors
    tau = _umath_linalg.qr_r_raw(reflectors, signature="d->d")
    return _umath_linalg.qr_complete(reflectors, tau, signature="dd->d")


def null_vector(A: np.ndarray) -> np.ndarray:
    """x = argmin ||A x|| s.t. ||x|| = 1: the last right singular vector of A (..., m, n) -> (..., n).

    The thin SVD suffices (and is much cheaper for tall A) unless A has fewer rows than columns. A minimal
    system (n - 1 rows, as a minimal sample gives) is solved by `minimal_null_vector` instead.
    """
    if A.shape[-2] == A.shape[-1] - 1:
        return minimal_null_vector(A)
    return svd(A, full_matrices=A.shape[-2] < A.shape[-1])[2][..., -1, :]


def solve_or_nan(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """w = a^-1 b for stacked systems a (R, n, n), b (R, n, k); NaN where a is singular (an exact zero
    pivot in its LU: det a = 0) or holds NaN."""
    # The gufunc behind np.linalg.solve leaves a singular system's solution NaN and raises the 'invalid'
    # flag, which np.linalg.solve turns into an error for the whole stack: called directly, one LU per
    # system however many are singular (SIFT's repeated keypoints make a singular minimal sample common:
    # 899 of lego's 1564 batches of minimal F and H samples hold one).
    with np.errstate(invalid="ignore"):
        return _umath_linalg.solve(a, b, signature="dd->d")


def minimal_null_vector(A: np.ndarray) -> np.ndarray:
    """x ~ [-B^-1 a; 1] with A = [B a] (..., n - 1, n) of rank n - 1, scaled to ||x|| = 1: A x = 0.

    LU with partial pivoting is backward stable, so x is the exact null vector of a matrix within
    machine precision of A (as accurate as the SVD's, at a fraction of its cost), however small x's last
    entry. Where B is exactly singular (a sample repeating a correspondence: SIFT puts several
    orientations on one keypoint) the SVD gives a vector of the null space.
    """
    systems = A.reshape(-1, *A.shape[-2:])
    x = np.ones((len(systems), A.shape[-1]))
    x[:, :-1] = solve_or_nan(systems[:, :, :-1], -systems[:, :, -1:])[..., 0]
    singular = np.isnan(x[:, 0])
    if singular.any():            # (an SVD of no systems still costs a LAPACK call's overhead)
        x[singular] = svd(systems[singular])[2][:, -1, :]
    x /= np.sqrt((x * x).sum(axis=1, keepdims=True))
    return x.reshape(*A.shape[:-2], A.shape[-1])


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x with [v]x w = v x w, batched over v (..., 3) -> (..., 3, 3)."""
    zero = np.zeros_like(v[..., 0])
    return np.stack([np.stack([zero, -v[..., 2], v[..., 1]], axis=-1),
                     np.stack([v[..., 2], zero, -v[..., 0]], axis=-1),
                     np.stack([-v[..., 1], v[..., 0], zero], axis=-1)], axis=-2)


def rotation_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: R = I + sinc(theta) [w]x + (1 - cos theta) / theta^2 [w]x^2, theta = ||w||; (..., 3) ->
    (..., 3, 3).

    (1 - cos theta) / theta^2 is written 0.5 sinc(theta / 2)^2, which has no cancellation near theta = 0.
    """
    w = np.asarray(rotvec, float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    cross = skew(w)
    # numpy's sinc is the normalized sin(pi x) / (pi x).
    return (np.eye(3) + np.sinc(theta / np.pi) * cross
            + 0.5 * np.sinc(theta / (2 * np.pi)) ** 2 * (cross @ cross))


def levenberg_marquardt(residuals: Callable[[np.ndarray], np.ndarray],
                        jacobian: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, ftol: float,
                        xtol: float, max_iterations: int = LM_MAX_ITERATIONS) -> np.ndarray:
    """x = argmin ||r(x)||^2 from x0 by steps (J^T J + lambda diag(J^T J)) dx = -J^T r, lambda / 10 after a
    step that lowers the cost and x 10 after one that does not. Stops once an accepted step lowers the cost
    by at most ftol relative, or a step is at most xtol (||x|| + xtol) long (MINPACK's criteria).

    For small dense problems (a few parameters) where scipy.optimize's import would cost more than the solve.
    """
    x = np.array(x0, float)
    r = residuals(x)
    cost = float(r @ r)
    damping = LM_INITIAL_DAMPING
    J = jacobian(x)
    for _ in range(max_iterations):
        normal = J.T @ J
        # A tiny floor keeps directions the residuals ignore (a gauge, e.g. a scale) solvable.
        system = normal + damping * np.diag(np.maximum(np.diag(normal), LM_DIAGONAL_FLOOR))
        step = np.linalg.solve(system, -(J.T @ r))
        if np.linalg.norm(step) <= xtol * (np.linalg.norm(x) + xtol):
            break
        trial = residuals(x + step)
        trial_cost = float(trial @ trial)
        if trial_cost >= cost:
            damping *= 10.0
            continue
        decrease = (cost - trial_cost) / max(cost, np.finfo(float).tiny)
        x, r, cost = x + step, trial, trial_cost
        damping /= 10.0
        if decrease <= ftol:
            break
        J = jacobian(x)
    return x
