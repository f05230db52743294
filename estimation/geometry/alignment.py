"""Similarity alignment of reconstructions to ground truth (SfM recovers the world up to s, R, t)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.types import CameraPose


class Similarity(NamedTuple):
    """X' = scale * R @ X + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """X' = s R X + t for points (N, 3)."""
        return self.scale * points @ self.R.T + self.t

    def apply_pose(self, pose: CameraPose) -> CameraPose:
        """The same camera in the transformed world: R' = R_cam R^T, C' = s R C + t."""
        return CameraPose.from_center(pose.R @ self.R.T, self.apply_points(pose.center[None])[0])


def align_similarity(source: np.ndarray, target: np.ndarray) -> Similarity:
    """Umeyama: argmin_{s,R,t} sum ||target_i - (s R source_i + t)||^2 over points (N, 3), N >= 3."""
    source, target = np.asarray(source, float), np.asarray(target, float)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    s_c, t_c = source - mu_s, target - mu_t
    U, D, Vt = np.linalg.svd(t_c.T @ s_c / len(source))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / (s_c**2).sum(axis=1).mean())
    return Similarity(scale=scale, R=R, t=mu_t - scale * R @ mu_s)


def rotation_angles_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle of R = R_a^T R_b: atan2(|vee(R - R^T)| / 2, (trace(R) - 1) / 2), in degrees, for
    stacked rotations (..., 3, 3) that broadcast against each other -> (...)."""
    R = np.swapaxes(R_a, -1, -2) @ R_b
    vee = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
                   axis=-1)
    sin_angle = np.sqrt(np.einsum("...k,...k->...", vee, vee)) / 2.0
    cos_angle = (np.einsum("...ii->...", R) - 1.0) / 2.0
    return np.degrees(np.arctan2(sin_angle, cos_angle))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """`rotation_angles_deg` of one pair of rotations."""
    return float(rotation_angles_deg(R_a, R_b))


class PoseErrors(NamedTuple):
    """Per-camera errors after similarity alignment of the estimated centres to the true ones."""

    rotation_deg: np.ndarray   # (M,)
    center: np.ndarray         # (M,) in ground-truth world units


def aligned_pose_errors(estimated: list[CameraPose], truth: list[CameraPose]) -> PoseErrors:
    """Align estimated camera centres onto the true ones (Umeyama), then compare each pose."""
    centers_estimated = np.array([p.center for p in estimated])
    similarity = align_similarity(centers_estimated, np.array([p.center for p in truth]))
    aligned = [similarity.apply_pose(p) for p in estimated]
    return PoseErrors(
        rotation_deg=rotation_angles_deg(np.array([a.R for a in aligned]), np.array([b.R for b in truth])),
        center=np.array([np.linalg.norm(a.center - b.center) for a, b in zip(aligned, truth, strict=True)]),
    )


def relative_rotation_errors_deg(estimated: list[CameraPose], truth: list[CameraPose]) -> np.ndarray:
    """`rotation_angles_deg` of R_i R_j^T against R*_i R*_j^T for every pair i < j (M (M - 1) / 2,): free of
    any alignment (a few nearly collinear centres pin a similarity's rotation poorly). ValueError unless
    both list the same cameras' poses (as many of each)."""
    if len(estimated) != len(truth):
        raise ValueError(f"relative rotation errors: {len(estimated)} estimated poses against {len(truth)} "
                         "true ones (one of each per camera)")
    R_estimated = np.array([p.R for p in estimated])
    R_true = np.array([p.R for p in truth])
    first, second = np.triu_indices(len(estimated), k=1)
    return rotation_angles_deg(R_estimated[first] @ np.swapaxes(R_estimated[second], -1, -2),
                               R_true[first] @ np.swapaxes(R_true[second], -1, -2))


def relative_pose(reference: CameraPose, other: CameraPose) -> CameraPose:
    """`other` in the frame of `reference`: R = R_o R_r^T, t = t_o - R t_r (reference: R = I, C = 0)."""
    R = other.R @ reference.R.T
    return CameraPose(R=R, t=other.t - R @ reference.t)
