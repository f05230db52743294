"""Null vectors of minimal systems (one row fewer than unknowns) by LU: as the SVD's, also where the
leading block is singular or the null vector's last entry is tiny."""

import numpy as np

from estimation.geometry.linalg import minimal_null_vector


def assert_unit_null_vectors(A: np.ndarray, x: np.ndarray) -> None:
    np.testing.assert_allclose(np.linalg.norm(x, axis=-1), 1.0)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", A, x), 0.0, atol=1e-12)


def test_minimal_null_vector_agrees_with_the_svd_up_to_sign():
    A = np.random.default_rng(0).standard_normal((64, 8, 9))
    x = minimal_null_vector(A)
    svd = np.linalg.svd(A)[2][:, -1]
    assert_unit_null_vectors(A, x)
    np.testing.assert_allclose(np.abs(np.einsum("bi,bi->b", x, svd)), 1.0, atol=1e-12)


def test_minimal_null_vector_of_one_system_has_no_batch_axis():
    A = np.random.default_rng(1).standard_normal((3, 4))
    x = minimal_null_vector(A)
    assert x.shape == (4,)
    assert_unit_null_vectors(A, x)


def test_a_repeated_row_still_gives_a_null_vector():
    # A sample repeating a correspondence: rank n - 2, the leading block is exactly singular.
    A = np.random.default_rng(2).standard_normal((4, 8, 9))
    A[1, 3] = A[1, 0]
    x = minimal_null_vector(A)
    assert_unit_null_vectors(A, x)


def test_a_null_vector_with_a_tiny_last_entry_is_accurate():
    rng = np.random.default_rng(3)
    truth = np.append(rng.standard_normal(8), 1e-13)
    truth /= np.linalg.norm(truth)
    # Rows orthogonal to the truth: A truth = 0 up to rounding.
    rows = rng.standard_normal((8, 9))
    A = rows - np.outer(rows @ truth, truth)
    x = minimal_null_vector(A)
    np.testing.assert_allclose(np.abs(x @ truth), 1.0, atol=1e-12)

