"""Triangulation of multi-view observations: linear DLT, then batched Levenberg-Marquardt on pixels.

Observations are flat: observation o sees point `point_index[o]` in a camera with pose
(`R[o]`, `t[o]`) at pixel `uv[o]`; every point has two or more observations. All points are solved
together (one vectorized 4x4 or 3x3 system per point), so thousands of points take milliseconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

NONLINEAR_ITERATIONS = 10
INITIAL_DAMPING = 1e-3


class Observations(NamedTuple):
    """Flat observations of points by posed cameras (world-to-camera R, t per observation)."""

    R: np.ndarray             # (O, 3, 3)
    t: np.ndarray             # (O, 3)
    uv: np.ndarray            # (O, 2) pixels
    point_index: np.ndarray   # (O,) int in [0, num_points)
    num_points: int


class Triangulation(NamedTuple):
    """Points and their mean reprojection error over their observations."""

    points: np.ndarray            # (P, 3)
    reprojection_px: np.ndarray   # (P,) mean over the point's observations


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


def reprojection_residuals(K: np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """r_o = pi(K (R_o X_p(o) + t_o)) - uv_o, (O, 2) pixels (depth clamped so behind-camera is large)."""
    x_cam = np.einsum("oij,oj->oi", obs.R, points[obs.point_index]) + obs.t
    depth = np.where(np.abs(x_cam[:, 2]) < 1e-12, 1e-12, x_cam[:, 2])
    u = K[0, 0] * x_cam[:, 0] / depth + K[0, 1] * x_cam[:, 1] / depth + K[0, 2]
    v = K[1, 1] * x_cam[:, 1] / depth + K[1, 2]
    return np.stack([u, v], axis=1) - obs.uv


def mean_reprojection_px(K: np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """Mean over each point's observations of ||r_o|| (pixels), (P,)."""
    error = np.linalg.norm(reprojection_residuals(K, obs, points), axis=1)
    counts = np.bincount(obs.point_index, minlength=obs.num_points)
    return np.bincount(obs.point_index, weights=error, minlength=obs.num_points) / np.maximum(counts, 1)


def triangulate_linear(K: np.ndarray, obs: Observations) -> Triangulation:
    """DLT: X = argmin ||A X||, ||X|| = 1, rows x_o x (R_o|t_o) X = 0 on normalized x_o = K^-1 [u v 1]."""
    uv1 = np.hstack([obs.uv, np.ones((len(obs.uv), 1))])
    x = uv1 @ np.linalg.inv(K).T
    P = np.concatenate([obs.R, obs.t[:, :, None]], axis=2)                 # (O, 3, 4)
    rows = np.stack([x[:, 0:1] * P[:, 2] - P[:, 0], x[:, 1:2] * P[:, 2] - P[:, 1]], axis=1)  # (O, 2, 4)
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    normal = np.einsum("oki,okj->oij", rows, rows)                           # (O, 4, 4) per-observation A^T A
    AtA = np.zeros((obs.num_points, 4, 4))
    np.add.at(AtA, obs.point_index, normal)
    homogeneous = np.linalg.eigh(AtA)[1][:, :, 0]        # eigenvector of the smallest eigenvalue
    w = homogeneous[:, 3]
    w = np.where(np.abs(w) < 1e-15, 1e-15, w)
    points = homogeneous[:, :3] / w[:, None]
    return Triangulation(points=points, reprojection_px=mean_reprojection_px(K, obs, points))


def _projection_jacobian(K: np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """d pi(K (R X + t)) / dX = d pi / dx_cam @ R, (O, 2, 3)."""
    x_cam = np.einsum("oij,oj->oi", obs.R, points[obs.point_index]) + obs.t
    z = np.where(np.abs(x_cam[:, 2]) < 1e-12, 1e-12, x_cam[:, 2])
    du_dx = np.stack([np.full_like(z, K[0, 0]) / z, np.full_like(z, K[0, 1]) / z,
                      -(K[0, 0] * x_cam[:, 0] + K[0, 1] * x_cam[:, 1]) / z**2], axis=1)
    dv_dx = np.stack([np.zeros_like(z), K[1, 1] / z, -K[1, 1] * x_cam[:, 1] / z**2], axis=1)
    return np.stack([du_dx, dv_dx], axis=1) @ obs.R


def triangulate_nonlinear(K: np.ndarray, obs: Observations, initial: np.ndarray,
                          iterations: int = NONLINEAR_ITERATIONS) -> Triangulation:
    """X_p = argmin sum_o ||pi(K (R_o X_p + t_o)) - uv_o||^2 per point: batched Levenberg-Marquardt."""
    points = np.array(initial, float)
    damping = np.full(obs.num_points, INITIAL_DAMPING)

    def cost(candidate: np.ndarray) -> np.ndarray:
        squared = (reprojection_residuals(K, obs, candidate) ** 2).sum(axis=1)
        return np.bincount(obs.point_index, weights=squared, minlength=obs.num_points)

    current = cost(points)
    for _ in range(iterations):
        residuals = reprojection_residuals(K, obs, points)
        J = _projection_jacobian(K, obs, points)
        JtJ = np.zeros((obs.num_points, 3, 3))
        Jtr = np.zeros((obs.num_points, 3))
        np.add.at(JtJ, obs.point_index, np.einsum("oki,okj->oij", J, J))
        np.add.at(Jtr, obs.point_index, np.einsum("oki,ok->oi", J, residuals))
        diagonal = np.einsum("pii->pi", JtJ)
        system = JtJ + (damping[:, None] * diagonal)[:, :, None] * np.eye(3)
        step = np.linalg.solve(system + 1e-12 * np.eye(3), -Jtr[:, :, None])[:, :, 0]
        candidate = points + step
        trial = cost(candidate)
        better = trial < current
        points[better] = candidate[better]
        current = np.where(better, trial, current)
        damping = np.where(better, damping / 10.0, damping * 10.0)
    return Triangulation(points=points, reprojection_px=mean_reprojection_px(K, obs, points))


def triangulation_angle_deg(centers: np.ndarray, obs_point_index: np.ndarray, points: np.ndarray
                            ) -> np.ndarray:
    """Per point, the largest angle between two of its viewing rays X - C_o (degrees), (P,).

    `centers` (O, 3) is the camera centre of each observation.
    """
    rays = points[obs_point_index] - centers
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    order = np.argsort(obs_point_index, kind="stable")
    rays, owner = rays[order], obs_point_index[order]
    min_cosine = np.ones(len(points))
    # Observations of a point are contiguous after sorting: compare each with the ones `offset` after it.
    for offset in range(1, int(np.bincount(owner).max(initial=1))):
        same = owner[:-offset] == owner[offset:]
        cosine = (rays[:-offset][same] * rays[offset:][same]).sum(axis=1)
        np.minimum.at(min_cosine, owner[:-offset][same], cosine)
    return np.degrees(np.arccos(np.clip(min_cosine, -1.0, 1.0)))
