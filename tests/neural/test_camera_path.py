"""Capture detection and camera paths on synthetic camera sets with known answers, and on the Strecha
ground-truth cameras (a facade seen from one side)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from neural.camera_path import (
    CAPTURE_FRAME_EYE,
    CameraPathError,
    capture_frame,
    detect_capture,
    path_poses,
    pose_from_capture_frame,
)
from neural.inference import look_at

UP = np.array([0.0, 0.0, 1.0])


def ring(
    degrees: float, count: int, radius: float = 3.0, height: float = 1.0, start: float = 0.0
) -> np.ndarray:
    """count cameras on an arc of `degrees` (ends included unless a full circle) looking at the origin."""
    angles = np.radians(start + np.linspace(0.0, degrees, count, endpoint=degrees < 360.0))
    target = np.zeros(3)
    return np.stack(
        [look_at(np.array([radius * math.cos(a), radius * math.sin(a), height]), target, UP) for a in angles]
    )


def walk(count: int) -> np.ndarray:
    """count cameras along the x axis, all looking down +y (a corridor), parallel axes."""
    return np.stack([look_at(np.array([x, 0.0, 1.0]), np.array([x, 5.0, 1.0]), UP) for x in range(count)])


def test_a_full_ring_is_closed_and_covers_360_degrees_round_its_centre() -> None:
    capture = detect_capture(ring(360.0, 12)[np.random.default_rng(0).permutation(12)])
    assert capture.kind == "ring" and capture.closed
    assert capture.span_deg == 360.0
    np.testing.assert_allclose(capture.target, [0.0, 0.0, 0.0], atol=1e-9)


def test_an_arc_of_60_degrees_is_open_with_its_span_and_its_middle_camera_as_default() -> None:
    poses = ring(60.0, 7, start=-120.0)
    shuffled = np.random.default_rng(1).permutation(7)
    capture = detect_capture(poses[shuffled])
    assert capture.kind == "arc" and not capture.closed
    assert capture.span_deg == pytest.approx(60.0, abs=1e-6)
    # path order runs end to end along the arc, and the default is the middle one (index 3 before shuffling)
    assert list(shuffled[capture.order]) in ([0, 1, 2, 3, 4, 5, 6], [6, 5, 4, 3, 2, 1, 0])
    assert shuffled[capture.default_index] == 3


def test_a_ring_missing_a_side_is_an_arc() -> None:
    capture = detect_capture(ring(240.0, 9))
    assert capture.kind == "arc" and capture.span_deg == pytest.approx(240.0, abs=1e-6)


def test_parallel_cameras_along_a_line_are_a_walk_ordered_along_it() -> None:
    poses = walk(6)
    capture = detect_capture(poses[::-1])
    assert capture.kind == "walk" and capture.span_deg == 0.0
    centres_x = poses[::-1][capture.order][:, 0, 3]
    assert np.all(np.diff(centres_x) > 0) or np.all(np.diff(centres_x) < 0)
    assert poses[::-1][capture.default_index][0, 3] in (2.0, 3.0)


def test_no_cameras_is_an_error() -> None:
    with pytest.raises(CameraPathError, match="no registered cameras"):
        detect_capture(np.zeros((0, 4, 4)))


def test_a_ring_path_goes_round_once_through_every_camera_and_keeps_looking_inward() -> None:
    poses = ring(360.0, 8)
    capture = detect_capture(poses)
    frames = path_poses(poses, capture, 64)
    centres = frames[:, :3, 3]
    angles = np.unwrap(np.arctan2(centres[:, 1], centres[:, 0]))
    assert abs(abs(angles[-1] - angles[0]) - 2 * math.pi * 63 / 64) < 0.05  # once round, no more
    assert np.all(np.abs(np.diff(angles)) < 2 * math.pi / 64 * 1.5)  # smooth, no jumps
    for camera in poses[:, :3, 3]:  # through the cameras: every 8th frame sits on one
        assert np.min(np.linalg.norm(centres - camera, axis=1)) < 1e-6
    forwards = -frames[:, :3, 2]
    towards_axis = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    assert np.all(np.einsum("ni,ni->n", forwards, towards_axis) > 0.9)
    np.testing.assert_allclose(np.linalg.det(frames[:, :3, :3]), 1.0, atol=1e-9)


def test_an_arc_path_stays_within_the_arc_and_comes_back() -> None:
    poses = ring(60.0, 5)
    frames = path_poses(poses, detect_capture(poses), 20)
    angles = np.degrees(np.arctan2(frames[:, 1, 3], frames[:, 0, 3]))
    assert angles.min() > -1.0 and angles.max() < 61.0  # never round the back
    assert angles.max() - angles.min() > 55.0  # but the whole arc
    assert abs(angles[0] - angles[-1]) < 60.0 / 10 * 1.5  # the last frame is one step from the first


def test_a_single_camera_path_is_that_camera() -> None:
    poses = ring(360.0, 1)
    frames = path_poses(poses, detect_capture(poses), 3)
    np.testing.assert_allclose(frames, np.repeat(poses, 3, axis=0))


@pytest.mark.parametrize("poses", [ring(90.0, 5, radius=0.5, height=0.1, start=30.0), walk(4)],
                         ids=["arc", "walk"])  # fmt: skip
def test_a_blender_style_request_in_the_capture_frame_is_the_default_camera(poses: np.ndarray) -> None:
    capture = detect_capture(poses)
    frame = capture_frame(poses, capture)
    request = look_at(np.array(CAPTURE_FRAME_EYE), np.zeros(3), UP)  # z up, as in Blender scenes
    pose = pose_from_capture_frame(request, frame)
    default = poses[capture.default_index]
    np.testing.assert_allclose(pose[:3, 3], default[:3, 3], atol=1e-9)
    np.testing.assert_allclose(pose[:3, :3], default[:3, :3], atol=1e-9)  # level cameras: roll too
    # x stays horizontal; z is up tilted about x only
    np.testing.assert_allclose(frame[:3, 0] @ capture.up, 0.0, atol=1e-9)


def strecha_cameras(folder: Path) -> np.ndarray:
    """The published cameras as OpenGL camera-to-world matrices."""
    truth = json.loads((folder / "ground_truth.json").read_text())["cameras"]
    poses = []
    for camera in truth.values():
        rotation, translation = np.asarray(camera["R"]), np.asarray(camera["t"]).reshape(3)
        c2w = np.eye(4)
        c2w[:3, :3] = rotation.T @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
        c2w[:3, 3] = -rotation.T @ translation
        poses.append(c2w)
    return np.stack(poses)


@pytest.mark.parametrize("name", ["Herz-Jesus-P8", "fountain-P11"])
def test_a_strecha_facade_is_an_open_arc_whose_path_stays_among_the_photos(
    name: str, shared_data: Path
) -> None:
    poses = strecha_cameras(shared_data / "strecha" / name)
    capture = detect_capture(poses)
    assert capture.kind == "arc" and capture.span_deg < 180.0
    frames = path_poses(poses, capture, 36)
    centres = poses[:, :3, 3]
    spacing = np.median(np.linalg.norm(np.diff(centres[capture.order], axis=0), axis=1))
    nearest = np.min(np.linalg.norm(frames[:, None, :3, 3] - centres[None], axis=2), axis=1)
    assert nearest.max() < spacing  # every frame within one photo spacing of a photo's camera
    # each frame looks the way its nearest photo does (within 30 degrees)
    nearest_index = np.argmin(np.linalg.norm(frames[:, None, :3, 3] - centres[None], axis=2), axis=1)
    cosines = np.einsum("ni,ni->n", -frames[:, :3, 2], -poses[nearest_index, :3, 2])
    assert cosines.min() > math.cos(math.radians(30.0))


@pytest.mark.parametrize("num_frames", [2, 3, 8, 37])
def test_every_frame_of_an_open_path_is_a_distinct_pose(num_frames: int) -> None:
    poses = ring(60.0, 5)
    frames = path_poses(poses, detect_capture(poses), num_frames)
    assert len({tuple(np.round(frame[:3, 3], 9)) for frame in frames}) == num_frames
