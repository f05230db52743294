"""The direct LAPACK calls (svd, eigh, eigvals, inv, complete_q) bitwise numpy.linalg's. Null vectors of
minimal systems (one row fewer than unknowns) by LU: as the SVD's, also where the
leading block is singular or the null vector's last entry is tiny; stacked solves leaving the singular
systems NaN. Rotation vectors to matrices, and a small dense Levenberg-Marquardt reaching the minimum
scipy's finds."""

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from estimation.geometry.linalg import (
    complete_q,
    eigh,
    eigvals,
    inv,
    levenberg_marquardt,
    minimal_null_vector,
    rotation_from_rotvec,
    solve_or_nan,
    svd,
)


def test_direct_lapack_calls_are_bitwise_numpy_linalg_on_stacks_and_single_matrices():
    rng = np.random.default_rng(3)
    for shape in [(3, 3), (64, 3, 3), (64, 10, 10)]:
        a = rng.standard_normal(shape)
        symmetric = a @ a.swapaxes(-1, -2)
        for ours, numpys in zip(svd(a), np.linalg.svd(a), strict=True):
            np.testing.assert_array_equal(ours, numpys)
        for ours, numpys in zip(eigh(symmetric), np.linalg.eigh(symmetric), strict=True):
            np.testing.assert_array_equal(ours, numpys)
        np.testing.assert_array_equal(eigvals(a), np.linalg.eigvals(a))
        np.testing.assert_array_equal(inv(a), np.linalg.inv(a))
    tall = rng.standard_normal((200, 9))
    thin = np.linalg.svd(tall, full_matrices=False)
    for ours, numpys in zip(svd(tall, full_matrices=False), thin, strict=True):
        np.testing.assert_array_equal(ours, numpys)


def test_complete_q_is_numpys_and_leaves_its_input_alone():
    a = np.random.default_rng(4).standard_normal((64, 5, 9)).swapaxes(-1, -2)      # a strided view
    before = a.copy()
    np.testing.assert_array_equal(complete_q(a), np.linalg.qr(a, mode="complete")[0])
    np.testing.assert_array_equal(a, before)


def test_eigvals_keeps_a_complex_pair_complex():
    rotation = np.array([[0.0, -1.0], [1.0, 0.0]])
    np.testing.assert_allclose(np.sort_complex(eigvals(rotation)), [-1j, 1j])


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



def test_a_singular_or_non_finite_system_gives_nan_and_leaves_the_others_solved():
    a = np.stack([np.diag([2.0, 4.0]), np.zeros((2, 2)), np.full((2, 2), np.nan)])
    w = solve_or_nan(a, np.ones((3, 2, 1)))[..., 0]
    np.testing.assert_array_equal(w, [[0.5, 0.25], [np.nan, np.nan], [np.nan, np.nan]])


def test_rotation_from_rotvec_is_scipys_rotation_at_every_angle_including_zero():
    rng = np.random.default_rng(4)
    axes = rng.standard_normal((6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([0.0, 1e-9, 1e-7, 0.3, 2.0, 3.1])          # zero and the Jacobian's steps too
    rotvecs = axes * angles[:, None]
    np.testing.assert_allclose(rotation_from_rotvec(rotvecs), Rotation.from_rotvec(rotvecs).as_matrix(),
                               atol=1e-15)
    np.testing.assert_array_equal(rotation_from_rotvec(np.zeros(3)), np.eye(3))


def exponential_fit_problem():
    """Residuals r_i = a exp(b s_i) + c - y_i of a noisy exponential, and their analytic Jacobian."""
    s = np.linspace(0.0, 2.0, 40)
    y = 2.0 * np.exp(-1.3 * s) + 0.5 + 0.01 * np.random.default_rng(5).standard_normal(40)

    def residuals(x):
        return x[0] * np.exp(x[1] * s) + x[2] - y

    def jacobian(x):
        return np.stack([np.exp(x[1] * s), x[0] * s * np.exp(x[1] * s), np.ones_like(s)], axis=1)

    return residuals, jacobian


def test_levenberg_marquardt_reaches_the_minimum_scipys_least_squares_finds():
    residuals, jacobian = exponential_fit_problem()
    start = np.array([1.0, 0.0, 0.0])
    ours = levenberg_marquardt(residuals, jacobian, start, ftol=1e-10, xtol=1e-10)
    theirs = least_squares(residuals, start, jac=jacobian, method="lm", ftol=1e-10, xtol=1e-10).x
    np.testing.assert_allclose(ours, theirs, rtol=1e-6)
    cost = residuals(ours) @ residuals(ours)
    assert cost < residuals(start) @ residuals(start) / 100


def test_levenberg_marquardt_stops_at_ftol_near_the_minimum():
    residuals, jacobian = exponential_fit_problem()
    start = np.array([1.0, 0.0, 0.0])
    loose = levenberg_marquardt(residuals, jacobian, start, ftol=1e-2, xtol=1e-12)
    tight = levenberg_marquardt(residuals, jacobian, start, ftol=1e-12, xtol=1e-12)
    cost_loose, cost_tight = (residuals(x) @ residuals(x) for x in (loose, tight))
    assert cost_tight <= cost_loose < 1.5 * cost_tight
    assert not np.allclose(loose, tight, rtol=1e-9, atol=0)     # it did stop early
