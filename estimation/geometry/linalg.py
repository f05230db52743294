"""Small linear-algebra helpers shared by the geometric solvers."""

from __future__ import annotations

import numpy as np


def null_vector(A: np.ndarray) -> np.ndarray:
    """x = argmin ||A x|| s.t. ||x|| = 1: the last right singular vector of A (..., m, n) -> (..., n).

    The thin SVD suffices (and is much cheaper for tall A) unless A has fewer rows than columns. A minimal
    system (n - 1 rows, as a minimal sample gives) is solved by `minimal_null_vector` instead.
    """
    if A.shape[-2] == A.shape[-1] - 1:
        return minimal_null_vector(A)
    return np.linalg.svd(A, full_matrices=A.shape[-2] < A.shape[-1])[2][..., -1, :]


def minimal_null_vector(A: np.ndarray) -> np.ndarray:
    """x ~ [-B^-1 a; 1] with A = [B a] (..., n - 1, n) of rank n - 1, scaled to ||x|| = 1: A x = 0.

    LU with partial pivoting is backward stable, so x is the exact null vector of a matrix within
    machine precision of A (as accurate as the SVD's, at a fraction of its cost), however small x's last
    entry. Where B is exactly singular (a sample repeating a correspondence: SIFT puts several
    orientations on one keypoint) the SVD gives a vector of the null space.
    """
    systems = A.reshape(-1, *A.shape[-2:])
    leading_block = systems[:, :, :-1]
    regular = np.linalg.det(leading_block) != 0.0
    x = np.ones((len(systems), A.shape[-1]))
    x[regular, :-1] = np.linalg.solve(leading_block[regular], -systems[regular, :, -1:])[..., 0]
    x[~regular] = np.linalg.svd(systems[~regular])[2][:, -1, :]
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x.reshape(*A.shape[:-2], A.shape[-1])
