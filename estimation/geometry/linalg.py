"""Small linear-algebra helpers shared by the geometric solvers."""

from __future__ import annotations

import numpy as np


def null_vector(A: np.ndarray) -> np.ndarray:
    """x = argmin ||A x|| s.t. ||x|| = 1: the last right singular vector of A (..., m, n) -> (..., n).

    The thin SVD suffices (and is much cheaper for tall A) unless A has fewer rows than columns.
    """
    return np.linalg.svd(A, full_matrices=A.shape[-2] < A.shape[-1])[2][..., -1, :]
