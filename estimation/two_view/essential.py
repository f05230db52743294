"""Essential matrix: the minimal 5-point solver in RANSAC, or E = K^T F K from F (the seed's path);
its four pose candidates and chirality disambiguation.

The first camera is the world frame (R = I, C = 0); candidates are the second camera's pose.
The 5-point solver is Stewenius' Groebner-basis formulation, batched over samples: E = x X + y Y + z Z + W
in the null space of the five epipolar rows, det(E) = 0 and 2 E E^T E - tr(E E^T) E = 0 give ten cubics
in (x, y, z), eliminated to the ten cubic monomials; the action matrix of x on the quotient basis of the
ten monomials of degree <= 2 has the (up to ten) real solutions' x as eigenvalues; y and z at each follow
from five of the eigen-equation's rows, a 5 x 5 linear solve (cheaper than eig's eigenvectors).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.geometry.linalg import (
    complete_q,
    eigvals,
    inv,
    levenberg_marquardt,
    rotation_from_rotvec,
    skew,
    solve_or_nan,
    svd,
)
from estimation.geometry.ransac import ransac
from estimation.geometry.triangulation import observations_for_pair, triangulate_linear
from estimation.two_view.fundamental import eight_point, epipolar_rows, sampson_distance, sampson_residual
from estimation.types import CameraPose

W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
FIVE_POINT_SAMPLE = 5
REAL_ROOT_TOLERANCE = 1e-9
"""An eigenvalue of the action matrix is a real root when |imag| < this * (1 + |real|)."""


class EssentialResult(NamedTuple):
    """x2^T E x1 = 0 for the inliers (normalized coordinates x = K^-1 [u v 1])."""

    E: np.ndarray                 # (3, 3), up to scale
    inlier_mask: np.ndarray       # (N,) bool
    sampson_px: np.ndarray        # (N,) Sampson distance in pixels under F = K2^-T E K1^-1
    iterations: int


def _monomials(max_degree: int) -> list[tuple[int, int, int]]:
    """Exponents (i, j, k) of x^i y^j z^k with degree <= max_degree, highest degree first."""
    return [(i, j, degree - i - j) for degree in range(max_degree, -1, -1)
            for i in range(degree, -1, -1) for j in range(degree - i, -1, -1)]


def _product_table(left: list, right: list, result: list) -> np.ndarray:
    """T with (a (x) b) @ T = a * b for polynomials a, b, a * b given as coefficients on these monomials."""
    position = {monomial: k for k, monomial in enumerate(result)}
    table = np.zeros((len(left) * len(right), len(result)))
    for a, left_monomial in enumerate(left):
        for b, right_monomial in enumerate(right):
            product = tuple(p + q for p, q in zip(left_monomial, right_monomial, strict=True))
            table[a * len(right) + b, position[product]] = 1.0
    return table


LINEAR, QUADRATIC, CUBIC = _monomials(1), _monomials(2), _monomials(3)
"""Monomial orders: LINEAR = (x, y, z, 1); CUBIC = the ten of degree 3, then QUADRATIC (quotient basis)."""
LINEAR_TIMES_LINEAR = _product_table(LINEAR, LINEAR, QUADRATIC)
QUADRATIC_TIMES_LINEAR = _product_table(QUADRATIC, LINEAR, CUBIC)
X_TIMES_BASIS = np.array([CUBIC.index((i + 1, j, k)) for i, j, k in CUBIC[10:]])
"""Position in CUBIC of x * b for each basis monomial b = CUBIC[10:]."""
ACTION_CUBIC_ROWS, ACTION_BASIS_ROWS = np.flatnonzero(X_TIMES_BASIS < 10), np.flatnonzero(X_TIMES_BASIS >= 10)
"""Rows of the action matrix whose x * b is a cubic monomial (reduced by the constraints) or a basis one."""


DIAGONAL = np.arange(3)
"""Indices of a 3 x 3 matrix's diagonal."""
ROOT_ROWS = np.arange(5)
"""`_yz_of_roots`' rows k, the action matrix's rows k + 1, which meet M's diagonal at column k + 1."""
FIRST_ROW_COFACTOR_SIGNS = np.array([1.0, -1.0, 1.0])
ESSENTIAL_SINGULAR_VALUES = np.diag([1.0, 1.0, 0.0])
"""An essential matrix's singular values (up to scale), as the diagonal matrix `project_to_essential` puts
between U and V^T."""
"""det E = sum_k (-1)^k E_0k M_0k, M_0k the minor of E_0k."""


def _null_space_basis(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(B, 4, 9) orthonormal basis of the null space of the five epipolar rows A: Q's last four columns in
    A^T = Q R (a complete QR: a third of the cost of eigh(A^T A), and no squared condition number)."""
    rows = epipolar_rows(x1, x2)
    return complete_q(rows.swapaxes(-1, -2))[..., 5:].swapaxes(-1, -2)


def _cubic_constraints(E: np.ndarray) -> np.ndarray:
    """(B, 10, 20) coefficients on CUBIC of 2 E E^T E - tr(E E^T) E = 0 (nine) and det E = 0, for E
    (B, 3, 3, 4) linear in (x, y, z, 1). Products of coefficient vectors are outer products, summed over
    the matrix index before they are mapped to monomials (LINEAR_TIMES_LINEAR, QUADRATIC_TIMES_LINEAR)."""
    num = len(E)
    # The coefficient products go through the tables as one 2-D matrix product each (a stacked matmul
    # would loop over the leading axes).
    EEt = np.einsum("bika,bjkc->bijac", E, E, optimize=True).reshape(-1, 16) @ LINEAR_TIMES_LINEAR
    EEt = EEt.reshape(num, 3, 3, 10)
    trace = np.einsum("biiq->bq", EEt)
    products = np.empty((num, 10, 10, 4))
    # 2 E E^T E - tr(E E^T) E = (2 E E^T - tr(E E^T) I) E: the trace joins the left factor (a 3 x 3 x 10
    # update, not a broadcast over the 3 x 3 x 10 x 4 product) and the product is written into place.
    left = 2.0 * EEt
    left[:, DIAGONAL, DIAGONAL] -= trace[:, None, :]
    np.einsum("bikq,bkjc->bijqc", left, E, optimize=True, out=products[:, :9].reshape(num, 3, 3, 10, 4))
    minors = (E[:, 1, [1, 0, 0], :, None] * E[:, 2, [2, 2, 1], None, :]
              - E[:, 1, [2, 2, 1], :, None] * E[:, 2, [1, 0, 0], None, :])
    minors = (minors.reshape(-1, 16) @ LINEAR_TIMES_LINEAR).reshape(num, 3, 10)
    products[:, 9] = np.einsum("k,bkq,bkc->bqc", FIRST_ROW_COFACTOR_SIGNS, minors, E[:, 0])
    return (products.reshape(-1, 40) @ QUADRATIC_TIMES_LINEAR).reshape(num, 10, 20)


def _real_roots(action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sample, x) of every real eigenvalue x of the action matrices (B, 10, 10): M v = x v, v the basis
    monomials at a root; eigenvalues only (LAPACK skips the Schur vectors: ~2/3 of eig's cost)."""
    values = eigvals(action)
    real = np.abs(values.imag) < REAL_ROOT_TOLERANCE * (1.0 + np.abs(values.real))
    sample, root = np.nonzero(real)
    return sample, values.real[sample, root]


def _yz_of_roots(action: np.ndarray, sample: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(y, z) at each root x of the action matrix M = action[sample] from rows 1..5 of (M - x I) v = 0,
    v = (x^2, xy, xz, y^2, yz, z^2, x, y, z, 1) linear in w = (y^2, yz, z^2, y, z, 1): a 5 x 5 solve
    per root."""
    rows = action[sample, 1:6]                                  # a copy: x I is subtracted in place
    rows[:, ROOT_ROWS, ROOT_ROWS + 1] -= x[:, None]
    x = x[:, None]
    system = np.empty((len(x), 5, 6))
    system[:, :, :3] = rows[:, :, 3:6]
    system[:, :, 3] = rows[:, :, 1] * x + rows[:, :, 7]
    system[:, :, 4] = rows[:, :, 2] * x + rows[:, :, 8]
    system[:, :, 5] = (rows[:, :, 0] * x + rows[:, :, 6]) * x + rows[:, :, 9]
    # Row 0 (x * x^2) is dropped: the six rows agree at a root; with it (normal equations on all six)
    # y, z strayed up to 1e-8 from eig's eigenvectors on synthetic samples, without it 1e-10.
    # A singular system (y, z not fixed by x alone, as when two roots share x) leaves that root NaN.
    w = solve_or_nan(system[:, :, :5], -system[:, :, 5:])[..., 0]
    return w[:, 3], w[:, 4]


def five_point_essential(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """All real E with x2^T E x1 = 0, det E = 0, 2 E E^T E = tr(E E^T) E from samples (B, 5, 2) of
    normalized coordinates; returns (M, 3, 3) unit-norm matrices, M <= 10 B."""
    null_space = _null_space_basis(x1, x2)
    E = np.moveaxis(null_space, 1, -1).reshape(len(x1), 3, 3, 4)      # entries linear in (x, y, z, 1)
    constraints = _cubic_constraints(E)
    # Gauss-Jordan on the cubic monomials: cubic_r = -reduced[r] . basis; a degenerate sample (singular or
    # non-finite constraints) gives a non-finite reduction and is dropped.
    reduced = solve_or_nan(constraints[:, :, :10], constraints[:, :, 10:])
    solved = np.isfinite(reduced).all(axis=(1, 2))
    reduced, null_space = reduced[solved], null_space[solved]
    action = np.zeros((len(reduced), 10, 10))
    action[:, ACTION_CUBIC_ROWS] = -reduced[:, X_TIMES_BASIS[ACTION_CUBIC_ROWS]]
    action[:, ACTION_BASIS_ROWS, X_TIMES_BASIS[ACTION_BASIS_ROWS] - 10] = 1.0
    sample, x = _real_roots(action)
    y, z = _yz_of_roots(action, sample, x)
    solutions = np.einsum("rk,rkj->rj", np.stack([x, y, z, np.ones_like(x)], axis=1),
                          null_space[sample]).reshape(-1, 3, 3)
    solutions = solutions[np.isfinite(solutions).all(axis=(1, 2))]
    return solutions / np.linalg.norm(solutions, axis=(1, 2), keepdims=True)


def normalizer(K: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """uv -> x = K^-1 [u v 1] (dehomogenized), for points (..., 2), with K inverted once."""
    principal_point, inverse_T = K[:2, 2], inv(K[:2, :2]).T
    return lambda uv: (uv - principal_point) @ inverse_T


def to_normalized(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """x = K^-1 [u v 1] (dehomogenized), for points (..., 2)."""
    return normalizer(K)(uv)


def fundamental_from_essential(E: np.ndarray, K1: np.ndarray, K2: np.ndarray) -> np.ndarray:
    """F = K2^-T E K1^-1 (batched over E)."""
    return np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)


def project_to_essential(E: np.ndarray) -> np.ndarray:
    """The closest essential matrix up to scale: singular values replaced by (1, 1, 0)."""
    U, _, Vt = svd(E)
    return U @ ESSENTIAL_SINGULAR_VALUES @ Vt


class RelativePose(NamedTuple):
    """Second camera's pose relative to the first (R = I, C = 0), with the linear points it implies."""

    pose: CameraPose
    points: np.ndarray          # (N, 3) linear triangulation under `pose`
    in_front: np.ndarray        # (N,) bool: r3 . (X - C) > 0 in both cameras
    candidate_scores: list[int]  # points in front of both cameras, per candidate


def essential_from_fundamental(F: np.ndarray, K: np.ndarray) -> np.ndarray:
    """E = K^T F K with its singular values projected to (1, 1, 0)."""
    return project_to_essential(K.T @ F @ K)


def _rotations_of_svd(U: np.ndarray, Vt: np.ndarray) -> np.ndarray:
    """R in {U W V^T, U W^T V^T}, each flipped to det R = +1 (E and -E describe the same geometry), for
    stacked factors of E = U S V^T (..., 3, 3) -> (..., 2, 3, 3)."""
    rotations = U[..., None, :, :] @ np.stack([W, W.T]) @ Vt[..., None, :, :]
    return rotations * np.sign(np.linalg.det(rotations))[..., None, None]


def essential_rotations(E: np.ndarray) -> np.ndarray:
    """The two R with E ~ [t]x R, R in {U W V^T, U W^T V^T} (det R = +1; the true one and its twisted pair,
    180 deg about the baseline from it), of stacked E (..., 3, 3) -> (..., 2, 3, 3)."""
    U, _, Vt = np.linalg.svd(E)
    return _rotations_of_svd(U, Vt)


def pose_candidates(E: np.ndarray) -> list[CameraPose]:
    """The four (R, C) with E ~ [t]x R: R of `essential_rotations`, t = +-u3, C = -R^T t (one SVD)."""
    U, _, Vt = np.linalg.svd(E)
    return [CameraPose(R=R, t=sign * U[:, 2]) for R in _rotations_of_svd(U, Vt) for sign in (1.0, -1.0)]


def relative_rotations(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """R of each stacked E (P, 3, 3) whose pose (R, +-t) puts most of its normalized correspondences x1, x2
    (P, M, 2) in front of both cameras: z2 x2 = z1 R x1 + t with z1, z2 > 0 (depths from x2 x (z1 R x1 + t) =
    0), for many pairs at once -> (P, 3, 3)."""
    U, _, Vt = np.linalg.svd(E)
    R = _rotations_of_svd(U, Vt)                                       # (P, 2, 3, 3)
    t = U[:, None, :, 2]                                               # (P, 1, 3), up to sign
    h1, h2 = (np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1) for x in (x1, x2))
    rotated = np.einsum("prij,pmj->prmi", R, h1)                       # (P, 2, M, 3): R x1
    across = np.cross(h2[:, None], rotated)                            # x2 x R x1
    z1 = -np.einsum("prmi,prmi->prm", np.cross(h2[:, None], t[:, :, None]), across)
    z1 /= np.maximum(np.einsum("prmi,prmi->prm", across, across), 1e-300)
    z2 = z1 * rotated[..., 2] + t[:, :, None, 2]                       # (z1 R x1 + t)_z, x2_z = 1
    # t's sign flips both depths' signs together: a candidate R counts the points of either sign.
    agree = z1 * z2 > 0
    in_front = np.maximum((agree & (z1 > 0)).sum(-1), (agree & (z1 < 0)).sum(-1))   # (P, 2)
    return R[np.arange(len(E)), np.argmax(in_front, axis=1)]


def in_front_of_both(pose: CameraPose, points: np.ndarray) -> np.ndarray:
    """Chirality: r3 . (X - C) > 0 for the second camera and X_z > 0 for the first (R = I, C = 0)."""
    return (points[:, 2] > 0) & ((points - pose.center) @ pose.R[2] > 0)


def choose_relative_pose(E: np.ndarray, K: np.ndarray, uv1: np.ndarray, uv2: np.ndarray) -> RelativePose:
    """The candidate putting most linearly triangulated points in front of both cameras."""
    if len(uv1) < 1:
        raise DegenerateConfigurationError("no correspondences to disambiguate the relative pose with")
    best: RelativePose | None = None
    scores: list[int] = []
    for candidate in pose_candidates(E):
        obs = observations_for_pair(np.eye(3), np.zeros(3), candidate.R, candidate.t, uv1, uv2)
        points = triangulate_linear(K, obs).points
        in_front = in_front_of_both(candidate, points)
        scores.append(int(in_front.sum()))
        if best is None or scores[-1] > best.in_front.sum():
            best = RelativePose(pose=candidate, points=points, in_front=in_front, candidate_scores=[])
    return best._replace(candidate_scores=scores)


JACOBIAN_STEP = 1e-7
"""Forward-difference step of refine_essential's Jacobian (parameters are radians and unit-scale t)."""


def refine_essential(E: np.ndarray, uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray, K2: np.ndarray
                     ) -> np.ndarray:
    """min over E = [t]x exp([w]x) R0 of sum r_i^2, r_i the Sampson residual of F = K2^-T E K1^-1 in pixels
    (Levenberg-Marquardt on w and t, ||t|| fixed by normalization inside the residual). The Jacobian's
    six forward differences are evaluated as one batch of seven E (one numpy pass per LM iteration).
    numpy's own LM: importing scipy.optimize for this 6-parameter problem cost ~0.2 s CPU, 20x the solve."""
    start = pose_candidates(E)[0]          # any of the four factorizations E ~ [t]x R
    K2_inv_T, K1_inv = np.linalg.inv(K2).T, np.linalg.inv(K1)

    def essentials_of(params: np.ndarray) -> np.ndarray:
        """E for parameter rows (B, 6) -> (B, 3, 3)."""
        t = params[:, 3:] / np.linalg.norm(params[:, 3:], axis=1, keepdims=True)
        return skew(t) @ rotation_from_rotvec(params[:, :3]) @ start.R

    def residuals_of(params: np.ndarray) -> np.ndarray:
        return sampson_residual(K2_inv_T @ essentials_of(params) @ K1_inv, uv1, uv2)

    def jacobian(params: np.ndarray) -> np.ndarray:
        shifted = params + np.vstack([np.zeros(6), JACOBIAN_STEP * np.eye(6)])
        values = residuals_of(shifted)
        return ((values[1:] - values[0]) / JACOBIAN_STEP).T

    # A relative cost change of 1e-4 moves the pose by far less than the pixel noise: stop there.
    solution = levenberg_marquardt(lambda params: residuals_of(params[None])[0], jacobian,
                                   np.concatenate([np.zeros(3), start.t]), ftol=1e-4, xtol=1e-4)
    return essentials_of(solution[None])[0]


def polish_essential(estimate: EssentialResult, uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray,
                     K2: np.ndarray, threshold_px: float) -> EssentialResult:
    """`refine_essential` on the estimate's inliers, kept when it does not lose consensus."""
    inliers = estimate.inlier_mask
    E = refine_essential(estimate.E, uv1[inliers], uv2[inliers], K1, K2)
    distance = sampson_distance(fundamental_from_essential(E, K1, K2), uv1, uv2)
    if (distance < threshold_px).sum() < inliers.sum():
        return estimate
    return estimate._replace(E=E, inlier_mask=distance < threshold_px, sampson_px=distance)


def ransac_essential(uv1: np.ndarray, uv2: np.ndarray, K1: np.ndarray, K2: np.ndarray, threshold_px: float,
                     config: RansacConfig, refine: bool = True) -> EssentialResult:
    """E maximizing #{Sampson distance of F = K2^-T E K1^-1 < threshold_px}: minimal 5-point samples in the
    RANSAC driver, each new best E re-fitted by the 8-point algorithm on its normalized inliers (LO), and
    (with `refine`) the final E polished by `polish_essential`."""
    uv1, uv2 = np.asarray(uv1, float), np.asarray(uv2, float)
    # K's inverses taken once per pair, not once per batch, refit and scoring (as to_normalized and
    # fundamental_from_essential would: ~6000 inversions on lego's pairs).
    normalized1, normalized2 = normalizer(K1), normalizer(K2)
    K2_inv_T, K1_inv = inv(K2).T, inv(K1)

    def minimal(sample1: np.ndarray, sample2: np.ndarray) -> np.ndarray:
        return five_point_essential(normalized1(sample1), normalized2(sample2))

    def residuals(E: np.ndarray, points1: np.ndarray, points2: np.ndarray) -> np.ndarray:
        return sampson_distance(K2_inv_T @ E @ K1_inv, points1, points2)

    def refit(inliers1: np.ndarray, inliers2: np.ndarray) -> np.ndarray:
        return project_to_essential(eight_point(normalized1(inliers1), normalized2(inliers2)))[None]

    result = ransac((uv1, uv2), minimal, FIVE_POINT_SAMPLE, residuals, threshold_px, config, refit=refit,
                    model_name="essential matrix")
    estimate = EssentialResult(E=result.model, inlier_mask=result.inlier_mask, sampson_px=result.residuals,
                               iterations=result.iterations)
    return polish_essential(estimate, uv1, uv2, K1, K2, threshold_px) if refine else estimate
