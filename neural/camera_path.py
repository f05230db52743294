"""Where the photos were: the kind of capture, a default view and a smooth camera path through the cameras.

Poses are camera-to-world (4,4) matrices with OpenGL camera axes (x right, y up, looking down -z), in any
one frame (the run's scene frame in practice); every function here is pure numpy/scipy on them.

A capture is one of
- "ring": the optical axes converge on a point and the centres go all the way round it (a closed path);
- "arc": the axes converge but the centres cover only part of the circle (a facade, a forward-facing
  capture): the path runs from one end camera to the other and back, never round the back;
- "walk": the axes do not converge (cameras moving through a scene): the path follows the centres along
  their main direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

CaptureKind = Literal["ring", "arc", "walk"]

#: The optical axes converge when they pass this close to their common point, relative to the distance
#: from the cameras to it (0.35 ~ within 20 degrees of the point as seen from the camera).
CONVERGENCE_RATIO = 0.35
#: Fewest cameras (as a fraction) that must have the convergence point in front of them.
IN_FRONT_FRACTION = 0.8
#: A ring closes when its largest angular gap between neighbouring centres is at most this ...
RING_MAX_GAP_DEG = 90.0
#: ... and at most this many times the median gap (one missing photo, not a missing side).
RING_GAP_TO_MEDIAN = 2.5
#: The plane of the centres gives up when its normal is within this angle of the cameras' mean up (else the
#: centres lie across the view, as in a forward-facing capture, and the mean up is used).
PLANE_UP_MAX_DEG = 30.0
#: Centres along a line (second singular value below this fraction of the first) give no plane.
COLLINEAR_RATIO = 0.1
#: In the capture frame the default camera stands here looking at the origin (the Blender scenes' example
#: view, z up), so that a Blender-style request (eye [0, -4, 1], look_at [0, 0, 0]) is the default photo's.
CAPTURE_FRAME_EYE = (0.0, -4.0, 1.0)


class CameraPathError(ValueError):
    """The cameras cannot give a path (none given, or not camera-to-world matrices)."""


@dataclass(frozen=True)
class Capture:
    """How the cameras were placed: kind, the point they look at, up, the angle they cover round it."""

    kind: CaptureKind
    target: np.ndarray
    """(3,) the point nearest every optical axis (walk: a point ahead of the default camera)."""
    up: np.ndarray
    """(3,) unit vector: the normal of the centres' plane, or the cameras' mean up."""
    span_deg: float
    """Angle covered by the centres round the target about up (360 for a ring, 0 for a walk)."""
    order: np.ndarray
    """Camera indices in path order (ring and arc: by angle, starting after the largest gap)."""
    default_index: int
    """The camera nearest the middle of the path: the default novel view."""

    @property
    def closed(self) -> bool:
        return self.kind == "ring"

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "target": self.target.tolist(),
            "up": self.up.tolist(),
            "span_deg": self.span_deg,
            "closed": self.closed,
            "order": self.order.tolist(),
            "default_index": self.default_index,
        }


def check_poses(c2w: np.ndarray) -> np.ndarray:
    """(N,4,4) float64 camera-to-world matrices with N >= 1, else CameraPathError."""
    poses = np.asarray(c2w, dtype=np.float64)
    if poses.size == 0:
        raise CameraPathError("no registered cameras: a camera path needs at least one")
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.isfinite(poses).all():
        raise CameraPathError(f"camera poses must be finite (N,4,4) matrices, got shape {poses.shape}")
    return poses


def capture_up(centres: np.ndarray, camera_ups: np.ndarray) -> np.ndarray:
    """Unit up: the normal of the centres' plane (min_n sum (n . (c_i - mean))^2) when it is near the
    cameras' mean up, else that mean (tilted towards the target when cameras look down on part of a ring)."""
    mean_up = camera_ups.mean(axis=0)
    mean_up = mean_up / max(np.linalg.norm(mean_up), 1e-12)
    if len(centres) >= 3:
        _, singular, axes = np.linalg.svd(centres - centres.mean(axis=0), full_matrices=False)
        normal = axes[2] * np.sign(axes[2] @ mean_up or 1.0)
        if singular[1] > COLLINEAR_RATIO * singular[0] and normal @ mean_up > math.cos(
            math.radians(PLANE_UP_MAX_DEG)
        ):
            return normal
    return mean_up


def axes_meeting_point(centres: np.ndarray, forwards: np.ndarray) -> np.ndarray | None:
    """The point nearest every optical axis, sum_i (I - f_i f_i^T)(x - c_i) = 0; None for parallel axes."""
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]
    lhs, rhs = projectors.sum(0), np.einsum("nij,nj->i", projectors, centres)
    eigenvalues = np.linalg.eigvalsh(lhs)
    if eigenvalues[0] < 1e-3 * len(centres):  # axes (nearly) parallel: the point is at infinity
        return None
    return np.linalg.solve(lhs, rhs)


def converges(centres: np.ndarray, forwards: np.ndarray, point: np.ndarray | None) -> bool:
    """The axes meet: the point lies in front of most cameras, each axis passing close to it."""
    if point is None or len(centres) < 2:
        return False
    offsets = point - centres
    depths = np.einsum("ni,ni->n", offsets, forwards)
    misses = np.linalg.norm(offsets - depths[:, None] * forwards, axis=1)
    in_front = depths > 0
    if in_front.mean() < IN_FRONT_FRACTION:
        return False
    return bool(np.median(misses[in_front]) <= CONVERGENCE_RATIO * np.median(depths[in_front]))


def angles_about(points: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Azimuth (radians, [0, 2 pi)) of each point round target about the unit axis up."""
    first = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    first /= np.linalg.norm(first)
    second = np.cross(up, first)
    offsets = points - target
    return np.mod(np.arctan2(offsets @ second, offsets @ first), 2 * math.pi)


def angular_order(angles: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(indices by angle starting after the largest gap, largest gap, all gaps), angles in radians."""
    order = np.argsort(angles)
    ordered = angles[order]
    gaps = np.diff(np.append(ordered, ordered[0] + 2 * math.pi))  # gaps[i]: from ordered[i] to the next
    largest = int(np.argmax(gaps))
    return np.roll(order, -(largest + 1)), float(gaps[largest]), gaps


def path_parameters(poses: np.ndarray, closed: bool, radius: float) -> np.ndarray:
    """Cumulative distance between consecutive poses (closed: back to the first too), counting a turn of
    angle a as a move of radius * a so that cameras turning in place still advance along the path."""
    following = np.concatenate([poses, poses[:1]]) if closed else poses
    moves = np.linalg.norm(np.diff(following[:, :3, 3], axis=0), axis=1)
    rotations = Rotation.from_matrix(following[:, :3, :3])
    turns = (rotations[1:] * rotations[:-1].inv()).magnitude()
    steps = np.sqrt(moves**2 + (radius * turns) ** 2)
    return np.concatenate([[0.0], np.cumsum(np.maximum(steps, 1e-9 * max(radius, 1e-9)))])


def detect_capture(c2w: np.ndarray) -> Capture:
    """The kind of capture of the cameras c2w (N,4,4), their target, up, span, path order and default."""
    poses = check_poses(c2w)
    centres, forwards = poses[:, :3, 3], -poses[:, :3, 2]
    up = capture_up(centres, poses[:, :3, 1])
    point = axes_meeting_point(centres, forwards)
    if converges(centres, forwards, point):
        angles = angles_about(centres, point, up)
        order, largest_gap, gaps = angular_order(angles)
        small_gap = largest_gap <= RING_GAP_TO_MEDIAN * np.median(gaps)
        closed = len(poses) >= 3 and math.degrees(largest_gap) <= RING_MAX_GAP_DEG and bool(small_gap)
        kind: CaptureKind = "ring" if closed else "arc"
        span = 360.0 if closed else 360.0 - math.degrees(largest_gap)
        target = point
    else:
        kind, span, closed = "walk", 0.0, False
        spread = centres - centres.mean(axis=0)
        direction = np.linalg.svd(spread, full_matrices=False)[2][0] if len(poses) > 1 else np.zeros(3)
        order = np.argsort(spread @ direction, kind="stable")
        target = None
    ordered = poses[order]
    radius = float(np.median(np.linalg.norm(centres - target, axis=1))) if target is not None else 1.0
    along = path_parameters(ordered, closed, radius)
    middle = int(np.argmin(np.abs(along[: len(order)] - 0.5 * along[len(order) - 1])))
    default_index = int(order[middle])
    if target is None:  # ahead of the default camera by the extent of the walk
        extent = max(float(np.ptp(centres, axis=0).max()), 1e-6) if len(poses) > 1 else 1.0
        target = centres[default_index] + extent * forwards[default_index]
    return Capture(kind, np.asarray(target, float), up, float(span), order, default_index)


def path_poses(c2w: np.ndarray, capture: Capture, num_frames: int) -> np.ndarray:
    """num_frames camera-to-world poses on a smooth path through the cameras, in their frame.

    Centres follow a cubic spline (periodic for a ring) and rotations a rotation spline, both through the
    cameras in path order, parametrised by distance along the path. A ring goes round once; an arc or a
    walk goes from its first camera to its last and back (slowing at the ends), so a looping video never
    jumps.
    """
    if num_frames < 1:
        raise CameraPathError(f"a camera path needs at least one frame, got {num_frames}")
    poses = check_poses(c2w)[capture.order]
    if len(poses) == 1:
        return np.repeat(poses, num_frames, axis=0)
    closed = capture.closed
    radius = float(np.median(np.linalg.norm(poses[:, :3, 3] - capture.target, axis=1)))
    knots = path_parameters(poses, closed, radius)
    centres, rotations = poses[:, :3, 3], poses[:, :3, :3]
    if closed:
        centres = np.concatenate([centres, centres[:1]])
        rotations = np.concatenate([rotations, rotations[:1]])
        samples = np.linspace(0.0, knots[-1], num_frames, endpoint=False)
    elif num_frames == 1:
        samples = np.array([0.5 * knots[-1]])
    else:  # there and back, easing at the end cameras; the quarter-frame phase keeps every frame distinct
        phases = 2 * math.pi * (np.arange(num_frames) + 0.25) / num_frames
        samples = 0.5 * (1.0 - np.cos(phases)) * knots[-1]
    boundary = "periodic" if closed else ("natural" if len(poses) > 2 else "not-a-knot")
    centre_spline = CubicSpline(knots, centres, bc_type=boundary)
    rotation_spline = RotationSpline(knots, Rotation.from_matrix(rotations))
    frames = np.tile(np.eye(4), (len(samples), 1, 1))
    frames[:, :3, 3] = centre_spline(samples)
    frames[:, :3, :3] = rotation_spline(samples).as_matrix()
    return frames


def capture_frame(c2w: np.ndarray, capture: Capture) -> np.ndarray:
    """(4,4) capture frame -> poses' frame, a similarity x' = s B x + o: the default camera at
    CAPTURE_FRAME_EYE looking at the origin o, which lies on its optical axis as far as the target; x
    horizontal to its right; z the capture's up tilted about x (by the eye's elevation less the camera's
    own pitch) so that the eye's direction is the camera's."""
    poses = check_poses(c2w)
    centre, forward = poses[capture.default_index, :3, 3], -poses[capture.default_index, :3, 2]
    depth = float((capture.target - centre) @ forward)
    if depth <= 0:  # the target is behind the camera (a walk seen from its end): one unit ahead
        depth = max(float(np.linalg.norm(capture.target - centre)), 1e-9)
    right = np.cross(forward, capture.up)
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: the camera's own right
        right = poses[capture.default_index, :3, 0]
    right /= np.linalg.norm(right)
    level_up = np.cross(right, forward)  # up, in the plane of the optical axis and the capture's up
    eye = np.asarray(CAPTURE_FRAME_EYE)
    elevation = math.atan2(eye[2], -eye[1])
    z_axis = -math.sin(elevation) * forward + math.cos(elevation) * level_up
    y_axis = math.cos(elevation) * forward + math.sin(elevation) * level_up
    frame = np.eye(4)
    frame[:3, :3] = depth / np.linalg.norm(eye) * np.stack([np.cross(y_axis, z_axis), y_axis, z_axis], axis=1)
    frame[:3, 3] = centre + depth * forward
    return frame


def pose_from_capture_frame(c2w_capture: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """A camera-to-world pose given in the capture frame -> the frame's target frame (rotation kept
    orthonormal: x' = s B x + t, R' = B R)."""
    scale = float(np.cbrt(np.linalg.det(frame[:3, :3])))
    pose = np.array(c2w_capture, dtype=np.float64, copy=True)
    pose[:3, :3] = frame[:3, :3] / scale @ pose[:3, :3]
    pose[:3, 3] = frame[:3, :3] @ pose[:3, 3] + frame[:3, 3]
    return pose
