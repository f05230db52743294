"""Triangulation of multi-view observations: linear DLT, then batched Levenberg-Marquardt on pixels.

Observations are flat: observation o sees point `point_index[o]` in a camera with pose
(`R[o]`, `t[o]`) at pixel `uv[o]`; every point has two or more observations. All points are solved
together (one vectorized 4x4 or 3x3 system per point), so thousands of points take milliseconds.
Rows of 2-D and 3-D arrays are gathered by `take` / `compress` (numpy 2's fancy and boolean row
indexing of such arrays costs 3-10 times more; the values are the same).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.geometry.projection import (
    Observations,
    as_camera,
    reprojection_errors,
    reprojection_residuals,
)

NONLINEAR_ITERATIONS = 10
INITIAL_DAMPING = 1e-3
STEP_TOLERANCE = 1e-8
"""Levenberg-Marquardt stops once every proposed step is below this fraction of its point's norm (scipy's
default xtol): on the mapper's points further steps move them by less than 1e-8 relative."""
IDENTITY_3 = np.eye(3)
SOLVE_REGULARIZATION = 1e-12 * IDENTITY_3
"""Added to each damped 3x3 system, so that a point seen along one ray still has a solution."""


class Triangulation(NamedTuple):
    """Triangulated points (their reprojection errors: `projection.reprojection_errors`, where a caller
    needs them)."""

    points: np.ndarray            # (P, 3)


def observations_for_pair(R1, t1, R2, t2, uv1: np.ndarray, uv2: np.ndarray) -> Observations:
    """Flat observations of N points seen by two cameras (point n observed at uv1[n] and uv2[n])."""
    n = len(uv1)
    return Observations(
        R=np.concatenate([np.broadcast_to(R1, (n, 3, 3)), np.broadcast_to(R2, (n, 3, 3))]),
        t=np.concatenate([np.broadcast_to(t1, (n, 3)), np.broadcast_to(t2, (n, 3))]),
        uv=np.concatenate([uv1, uv2]),
        point_index=np.concatenate([np.arange(n), np.arange(n)]),
        num_points=n,
    )


def sum_per_point(values: np.ndarray, point_index: np.ndarray, num_points: int) -> np.ndarray:
    """S_p = sum_{o : point_index[o] = p} values_o for values (O, ...) -> (P, ...).

    One bincount over the flattened entries (np.add.at's unbuffered scatter costs several times more)."""
    shape = values.shape[1:]
    width = int(np.prod(shape))
    bins = (point_index[:, None] * width + np.arange(width)).ravel()
    sums = np.bincount(bins, weights=values.reshape(-1), minlength=num_points * width)
    return sums.reshape((num_points, *shape))


def triangulate_linear(K: np.ndarray, obs: Observations) -> Triangulation:
    """DLT: X = argmin ||A X||, ||X|| = 1, rows x_o x (R_o|t_o) X = 0 on normalized x_o = K^-1 [u v 1]."""
    uv1 = np.hstack([obs.uv, np.ones((len(obs.uv), 1))])
    x = uv1 @ np.linalg.inv(K).T
    P = np.concatenate([obs.R, obs.t[:, :, None]], axis=2)                 # (O, 3, 4)
    rows = np.stack([x[:, 0:1] * P[:, 2] - P[:, 0], x[:, 1:2] * P[:, 2] - P[:, 1]], axis=1)  # (O, 2, 4)
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    normal = np.einsum("oki,okj->oij", rows, rows)                           # (O, 4, 4) per-observation A^T A
    AtA = sum_per_point(normal, obs.point_index, obs.num_points)
    homogeneous = np.linalg.eigh(AtA)[1][:, :, 0]        # eigenvector of the smallest eigenvalue
    w = homogeneous[:, 3]
    w = np.where(np.abs(w) < 1e-15, 1e-15, w)
    points = homogeneous[:, :3] / w[:, None]
    return Triangulation(points=points)


def _projection_jacobian(K: np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """d pi(K (R X + t)) / dX = A (R_12 - p r_3^T) / z, (O, 2, 3): A = K[:2, :2], p = x_cam[:2] / z the
    normalized point, R_12 and r_3 the first two rows and the last row of R."""
    x_cam = np.einsum("oij,oj->oi", obs.R, points.take(obs.point_index, axis=0)) + obs.t
    z = np.where(np.abs(x_cam[:, 2]) < 1e-12, 1e-12, x_cam[:, 2])
    d_normalized = (obs.R[:, :2] - (x_cam[:, :2] / z[:, None])[:, :, None] * obs.R[:, 2:3]) / z[:, None, None]
    return np.einsum("ij,ojk->oik", K[:2, :2], d_normalized)


def triangulate_nonlinear(K: np.ndarray, obs: Observations, initial: np.ndarray,
                          iterations: int = NONLINEAR_ITERATIONS) -> Triangulation:
    """X_p = argmin sum_o ||pi(K (R_o X_p + t_o)) - uv_o||^2 per point: batched Levenberg-Marquardt, until
    every step is below STEP_TOLERANCE relative or after `iterations`."""
    points = np.array(initial, float)
    damping = np.full(obs.num_points, INITIAL_DAMPING)
    camera = as_camera(K)   # built once for every projection below

    def cost(residuals: np.ndarray) -> np.ndarray:
        return np.bincount(obs.point_index, weights=(residuals**2).sum(axis=1), minlength=obs.num_points)

    residuals = reprojection_residuals(camera, obs, points)
    current = cost(residuals)
    for _ in range(iterations):
        J = _projection_jacobian(K, obs, points)
        # J^T J and J^T r of every observation, summed per point in one pass: (P, 9 + 3).
        sums = sum_per_point(np.concatenate([np.einsum("oki,okj->oij", J, J).reshape(-1, 9),
                                             np.einsum("oki,ok->oi", J, residuals)], axis=1),
                             obs.point_index, obs.num_points)
        JtJ, Jtr = sums[:, :9].reshape(-1, 3, 3), sums[:, 9:]
        diagonal = np.einsum("pii->pi", JtJ)
        system = JtJ + (damping[:, None] * diagonal)[:, :, None] * IDENTITY_3
        step = np.linalg.solve(system + SOLVE_REGULARIZATION, -Jtr[:, :, None])[:, :, 0]
        if np.all(np.linalg.norm(step, axis=1) <= STEP_TOLERANCE * (np.linalg.norm(points, axis=1)
                                                                    + STEP_TOLERANCE)):
            break
        candidate = points + step
        trial_residuals = reprojection_residuals(camera, obs, candidate)
        trial = cost(trial_residuals)
        better = trial < current
        points[better] = candidate[better]
        residuals = np.where(better[obs.point_index, None], trial_residuals, residuals)
        current = np.where(better, trial, current)
        damping = np.where(better, damping / 10.0, damping * 10.0)
    return Triangulation(points=points)


def triangulation_angle_deg(centers: np.ndarray, obs_point_index: np.ndarray, points: np.ndarray
                            ) -> np.ndarray:
    """Per point, the largest angle between two of its viewing rays X - C_o (degrees), (P,).

    `centers` (O, 3) is the camera centre of each observation.
    """
    rays = points.take(obs_point_index, axis=0) - centers
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    order = np.argsort(obs_point_index, kind="stable")
    rays, owner = rays[order], obs_point_index[order]
    min_cosine = np.ones(len(points))
    # Observations of a point are contiguous after sorting: compare each with the one `offset` after it.
    # An observation with no partner at this offset has none further on, so the pairs only shrink.
    first = np.arange(len(owner))
    offset = 1
    while len(first):
        first = first[first + offset < len(owner)]
        first = first[owner[first + offset] == owner[first]]
        cosine = np.einsum("oi,oi->o", rays[first], rays[first + offset])
        np.minimum.at(min_cosine, owner[first], cosine)
        offset += 1
    return np.degrees(np.arccos(np.clip(min_cosine, -1.0, 1.0)))


def ray_pair_angle_deg(centers: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per point, the angle between its two viewing rays X_p - C_p and X_p - C_{P+p} (degrees), (P,);
    centers (2P, 3). What `triangulation_angle_deg` gives for two observations per point, bitwise,
    without its sort and pair search."""
    rays = np.concatenate([points, points]) - centers
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    cosine = np.minimum(np.einsum("oi,oi->o", rays[: len(points)], rays[len(points):]), 1.0)
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def triangulation_angle_reaches(centers: np.ndarray, obs_point_index: np.ndarray, points: np.ndarray,
                                min_angle_deg: float) -> np.ndarray:
    """Per point, whether the largest angle between two of its viewing rays X - C_o reaches min_angle_deg,
    (P,) bool, False for a point without rays; `centers` (O, 3) is the camera centre of each observation.

    With a_o the angle of ray o to one reference ray of its point, max a_o <= largest angle <= 2 max a_o
    (the triangle inequality of angles): one pass over the observations decides every point but those
    with max a_o in [min_angle_deg / 2, min_angle_deg), whose `triangulation_angle_deg` is computed.
    """
    rays = points.take(obs_point_index, axis=0) - centers
    rays /= np.sqrt(np.einsum("oi,oi->o", rays, rays))[:, None]
    reference = np.zeros(len(points), np.int64)
    reference[obs_point_index] = np.arange(len(obs_point_index))   # any one observation of each point
    cosine = np.einsum("oi,oi->o", rays, rays.take(reference[obs_point_index], axis=0))
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))

    def some_ray_beyond(angle_deg: float) -> np.ndarray:
        """Per point: a_o >= angle_deg for some o (a count per point: no unbuffered ufunc.at)."""
        return np.bincount(obs_point_index, weights=angle >= angle_deg, minlength=len(points)) > 0

    reaches = some_ray_beyond(min_angle_deg)
    undecided = ~reaches & some_ray_beyond(min_angle_deg / 2)
    if undecided.any():
        subset = undecided[obs_point_index]
        compact = np.cumsum(undecided) - 1
        reaches[undecided] = triangulation_angle_deg(
            centers[subset], compact[obs_point_index[subset]], points[undecided]) >= min_angle_deg
    return reaches


class RobustTriangulation(NamedTuple):
    """Points from each track's best two-view hypothesis, refined on the observations agreeing with it."""

    points: np.ndarray        # (P, 3)
    inlier_mask: np.ndarray   # (O,) bool: observation within max_error_px of its point (in front)
    valid: np.ndarray         # (P,) bool: 2+ inliers seen at an angle of at least min_angle_deg


def triangulate_ransac(K: np.ndarray, obs: Observations, max_error_px: float, min_angle_deg: float,
                       hypotheses_per_point: int) -> RobustTriangulation:
    """Per point, argmax over pairs (a, b) of its observations of #{o : ||r_o(DLT(a, b))|| < max_error_px}
    (pairs under min_angle_deg or behind a camera score nothing), then non-linear on the consensus.

    All points at once: the point's first `hypotheses_per_point` observation pairs in triangular order
    (every pair when there are no more), scored against all of the point's observations in one
    vectorized pass.
    """
    order = np.argsort(obs.point_index, kind="stable")
    counts = np.bincount(obs.point_index, minlength=obs.num_points)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # Hypothesis h of point p pairs its (sorted) observations a and b < a in triangular order: h -> (a, b)
    # = (1, 0), (2, 0), (2, 1), (3, 0), ...; a point with fewer pairs has fewer hypotheses (no repeats).
    per_point = np.minimum(counts * (counts - 1) // 2, hypotheses_per_point)
    owner = np.repeat(np.arange(obs.num_points), per_point)                 # hypothesis -> its point
    first_of_point = np.cumsum(per_point) - per_point
    h = np.arange(len(owner)) - first_of_point[owner]
    a = np.floor((1 + np.sqrt(1 + 8 * h)) / 2).astype(np.int64)
    pair_obs = order[starts[owner] + np.stack([a, h - a * (a - 1) // 2])]   # (2, hypotheses)
    num_hypotheses = len(owner)
    hypothesis_obs = Observations(
        R=obs.R.take(pair_obs.ravel(), axis=0), t=obs.t.take(pair_obs.ravel(), axis=0),
        uv=obs.uv.take(pair_obs.ravel(), axis=0),
        point_index=np.tile(np.arange(num_hypotheses), 2), num_points=num_hypotheses)
    candidates = triangulate_linear(K, hypothesis_obs).points
    centers = -np.einsum("oji,oj->oi", hypothesis_obs.R, hypothesis_obs.t)
    pair_angle = ray_pair_angle_deg(centers, candidates)   # hypothesis h: observations h and H + h

    # Score each hypothesis of p on every observation of p: observation o is repeated per hypothesis.
    scored_per_obs = per_point[obs.point_index]
    scored_obs = np.repeat(np.arange(len(obs.uv)), scored_per_obs)
    scored_hypothesis = (first_of_point[obs.point_index[scored_obs]] + np.arange(len(scored_obs))
                         - np.repeat(np.cumsum(scored_per_obs) - scored_per_obs, scored_per_obs))
    expanded = Observations(R=obs.R.take(scored_obs, axis=0), t=obs.t.take(scored_obs, axis=0),
                            uv=obs.uv.take(scored_obs, axis=0),
                            point_index=scored_hypothesis, num_points=num_hypotheses)
    agrees = reprojection_errors(K, expanded, candidates) < max_error_px
    support = np.bincount(scored_hypothesis, weights=agrees, minlength=num_hypotheses)
    support[~((pair_angle >= min_angle_deg) & np.all(np.isfinite(candidates), axis=1))] = -1
    # Best hypothesis per point: the first of the largest support (the order of the listed pairs).
    ranked = np.lexsort((h, -support, owner))
    first_of_owner = np.ones(len(ranked), bool)
    first_of_owner[1:] = owner[ranked[1:]] != owner[ranked[:-1]]
    leaders = ranked[first_of_owner]
    best_hypothesis = np.full(obs.num_points, -1, np.int64)
    best_hypothesis[owner[leaders]] = leaders
    best_of_obs = best_hypothesis[obs.point_index]
    inliers = np.zeros(len(obs.uv), bool)
    inliers[scored_obs[agrees & (scored_hypothesis == best_of_obs[scored_obs])]] = True
    inliers &= (best_of_obs >= 0) & (support[best_of_obs] >= 2)

    subset = Observations(obs.R.compress(inliers, axis=0), obs.t.compress(inliers, axis=0),
                          obs.uv.compress(inliers, axis=0), obs.point_index[inliers], obs.num_points)
    points = np.where((best_hypothesis >= 0)[:, None], candidates.take(best_hypothesis, axis=0), np.nan)
    if inliers.any():
        points = triangulate_nonlinear(K, subset, points).points
    inliers = reprojection_errors(K, obs, points) < max_error_px
    inlier_counts = np.bincount(obs.point_index[inliers], minlength=obs.num_points)
    all_centers = -np.einsum("oji,oj->oi", obs.R.compress(inliers, axis=0), obs.t.compress(inliers, axis=0))
    wide = triangulation_angle_reaches(all_centers, obs.point_index[inliers], points, min_angle_deg)
    valid = (inlier_counts >= 2) & wide
    return RobustTriangulation(points=points, inlier_mask=inliers & valid[obs.point_index], valid=valid)
