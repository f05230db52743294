"""Exports: COLMAP text round trip, PLY round trip, and the transforms.json camera convention."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimation.errors import InputError
from estimation.io.export import (
    PIXEL_CENTER_SHIFT,
    opencv_pose_to_opengl_c2w,
    opengl_c2w_to_opencv_pose,
    quaternion_to_rotation,
    read_colmap_points,
    read_colmap_text,
    read_ply,
    read_ply_points,
    rotation_to_quaternion,
    transforms_dict,
    write_colmap_text,
    write_json,
    write_ply,
)
from estimation.synthetic import make_scene, project, rotation_about_axis


def random_rotations(count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    rotations = [rotation_about_axis(rng.normal(size=3), rng.uniform(-np.pi, np.pi)) for _ in range(count)]
    # Rotations by ~180 degrees about each axis exercise every branch of the quaternion extraction.
    rotations += [rotation_about_axis(axis, np.pi - 1e-9) for axis in np.eye(3)]
    return rotations


def test_quaternion_of_a_quarter_turn_about_z():
    q = rotation_to_quaternion(rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.pi / 2))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15)


@pytest.mark.parametrize("R", random_rotations(20), ids=lambda _: "R")
def test_rotation_quaternion_round_trip_with_nonnegative_scalar(R):
    q = rotation_to_quaternion(R)
    assert q[0] >= 0
    assert np.linalg.norm(q) == pytest.approx(1.0)
    np.testing.assert_allclose(quaternion_to_rotation(q), R, atol=1e-12)


def synthetic_model(unregistered: int = 2):
    """A synthetic scene written as a model in which image `unregistered` is missing."""
    scene = make_scene(num_cameras=5, num_points=60, noise_px=0.3, seed=3, visibility=0.7)
    tracks = scene.tracks
    keep = tracks.image_index != unregistered
    poses = {i: pose for i, pose in enumerate(scene.poses) if i != unregistered}
    errors = np.random.default_rng(0).uniform(0, 2, len(scene.points))
    return scene, poses, errors, tracks.image_index[keep], tracks.track_index[keep], tracks.uv[keep]


def test_colmap_text_round_trip_keeps_cameras_images_points_and_tracks(tmp_path):
    scene, poses, errors, obs_camera, obs_point, obs_uv = synthetic_model()
    names = scene.tracks.image_names
    write_colmap_text(tmp_path, scene.K, scene.width, scene.height, names, poses, scene.points, scene.colors,
                      errors, obs_camera, obs_point, obs_uv)
    model = read_colmap_text(tmp_path)

    np.testing.assert_allclose(model.K, scene.K, rtol=1e-12)
    assert (model.width, model.height) == (scene.width, scene.height)
    assert model.image_names == {i + 1: names[i] for i in poses}          # image id = index + 1
    for index, pose in poses.items():
        np.testing.assert_allclose(model.poses[index + 1].R, pose.R, atol=1e-12)
        np.testing.assert_allclose(model.poses[index + 1].t, pose.t, atol=1e-12)
    np.testing.assert_array_equal(model.point_ids, np.arange(1, len(scene.points) + 1))
    np.testing.assert_allclose(model.points, scene.points, rtol=1e-15)
    np.testing.assert_array_equal(model.colors, scene.colors)
    np.testing.assert_allclose(model.errors, errors, rtol=1e-15)

    # Every observation comes back: through the image's POINTS2D line and through the point's track.
    for index in poses:
        in_image = obs_camera == index
        expected = sorted(zip(obs_point[in_image] + 1, map(tuple, obs_uv[in_image]), strict=True))
        image_id = index + 1
        got = sorted(zip(model.image_point_ids[image_id], map(tuple, model.image_uv[image_id]), strict=True))
        assert [p for p, _ in got] == [p for p, _ in expected]
        np.testing.assert_allclose([uv for _, uv in got], [uv for _, uv in expected], atol=1e-12)
    for point_id, track in zip(model.point_ids, model.tracks, strict=True):
        for image_id, point2d_index in track:
            assert model.image_point_ids[image_id][point2d_index] == point_id
    assert sum(len(track) for track in model.tracks) == len(obs_camera)


def test_colmap_files_use_colmap_conventions(tmp_path):
    scene, poses, errors, obs_camera, obs_point, obs_uv = synthetic_model()
    write_colmap_text(tmp_path, scene.K, scene.width, scene.height, scene.tracks.image_names, poses,
                      scene.points, scene.colors, errors, obs_camera, obs_point, obs_uv)
    camera_line = [line for line in (tmp_path / "cameras.txt").read_text().splitlines() if line[0] != "#"]
    fx, fy, cx, cy = map(float, camera_line[0].split()[4:])
    assert camera_line[0].split()[:4] == ["1", "PINHOLE", "800", "600"]
    # COLMAP puts the corner of the top-left pixel at the origin: +0.5 from OpenCV's pixel centres.
    assert (fx, fy, cx, cy) == (scene.K[0, 0], scene.K[1, 1], scene.K[0, 2] + 0.5, scene.K[1, 2] + 0.5)
    image_lines = [line for line in (tmp_path / "images.txt").read_text().splitlines() if line[0] != "#"]
    first = image_lines[0].split()
    assert first[0] == "1" and first[-2:] == ["1", "1.png"]
    # images.txt holds world-to-camera: the camera centre is -R^T t.
    R, t = quaternion_to_rotation(np.array(first[1:5], float)), np.array(first[5:8], float)
    np.testing.assert_allclose(-R.T @ t, scene.poses[0].center, atol=1e-12)
    x, y, point_id = image_lines[1].split()[:3]
    observation = np.flatnonzero((obs_camera == 0) & (obs_point == int(point_id) - 1))[0]
    np.testing.assert_allclose([float(x), float(y)], obs_uv[observation] + PIXEL_CENTER_SHIFT, atol=1e-12)


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_round_trip_keeps_points_and_colours(tmp_path, binary):
    rng = np.random.default_rng(1)
    points = rng.normal(size=(50, 3)) * 10
    colors = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    path = tmp_path / "points.ply"
    write_ply(path, points, colors, binary=binary)
    header = path.read_bytes()[:200].decode("ascii", errors="replace")
    assert header.startswith("ply\nformat " + ("binary_little_endian" if binary else "ascii") + " 1.0\n")
    assert "element vertex 50\n" in header and "property uchar red" in header
    read_points, read_colors = read_ply(path)
    np.testing.assert_allclose(read_points, points, rtol=1e-6)          # stored as float32
    np.testing.assert_array_equal(read_colors, colors)


def test_ply_points_are_read_from_any_vertex_layout(tmp_path):
    path = tmp_path / "other.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty double nx\nproperty double z\n"
                    "property float x\nproperty float y\nelement face 0\nend_header\n0 3 1 2\n0 6 4 5\n")
    np.testing.assert_array_equal(read_ply_points(path), [[1, 2, 3], [4, 5, 6]])


def test_bad_ply_and_points3d_files_are_refused_naming_them(tmp_path):
    short = tmp_path / "short.ply"
    short.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
                      b"property float y\nproperty float z\nend_header\n" + bytes(12))
    with pytest.raises(InputError, match=r"short\.ply: file ends before its 3 vertices"):
        read_ply_points(short)
    points3d = tmp_path / "points3D.txt"
    points3d.write_text("# comment\n1 0.5 1.5 2.5 255 0 0 0.1 1 0\n2 1.0 oops 3\n")
    with pytest.raises(InputError, match=r"points3D\.txt, line 3: non-numeric"):
        read_colmap_points(points3d)
    points3d.write_text("1 0.5 1.5 2.5 255 0 0 0.1 1 0\n")
    np.testing.assert_array_equal(read_colmap_points(points3d), [[0.5, 1.5, 2.5]])


def test_transforms_json_frames_are_camera_to_world_in_opengl_axes(tmp_path):
    scene = make_scene(num_cameras=4, num_points=20, seed=5)
    frames = [(f"../images/{i + 1}.png", pose) for i, pose in enumerate(scene.poses)]
    content = transforms_dict(scene.K, 800, 600, frames, ply_file_path="points.ply")
    write_json(tmp_path / "transforms.json", content)
    content = json.loads((tmp_path / "transforms.json").read_text())
    assert (content["w"], content["h"]) == (800, 600)
    assert (content["fl_x"], content["fl_y"]) == (scene.K[0, 0], scene.K[1, 1])
    assert (content["cx"], content["cy"]) == (scene.K[0, 2] + 0.5, scene.K[1, 2] + 0.5)
    assert content["camera_angle_x"] == pytest.approx(2 * np.arctan(400 / scene.K[0, 0]))
    assert content["ply_file_path"] == "points.ply"
    assert [frame["file_path"] for frame in content["frames"]] == [path for path, _ in frames]

    for frame, pose in zip(content["frames"], scene.poses, strict=True):
        c2w = np.array(frame["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_array_equal(c2w[3], [0, 0, 0, 1])
        np.testing.assert_allclose(c2w[:3, 3], pose.center, atol=1e-12)        # translation = centre
        # OpenGL cameras look down their -z axis; the synthetic cameras all look at the origin.
        forward = -c2w[:3, 2]
        np.testing.assert_allclose(forward, pose.R[2], atol=1e-12)
        to_origin = -pose.center / np.linalg.norm(pose.center)
        assert forward @ to_origin > np.cos(np.deg2rad(5))
        # +y is up in OpenGL: the image's "up" (-v) direction.
        np.testing.assert_allclose(c2w[:3, 1], -pose.R[1], atol=1e-12)
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)

        # A pinhole in OpenGL axes with the exported intrinsics reproduces the OpenCV projection.
        in_camera = (np.linalg.inv(c2w) @ np.c_[scene.points, np.ones(len(scene.points))].T)[:3].T
        assert np.all(in_camera[:, 2] < 0)
        u = content["cx"] + content["fl_x"] * in_camera[:, 0] / -in_camera[:, 2] - 0.5
        v = content["cy"] - content["fl_y"] * in_camera[:, 1] / -in_camera[:, 2] - 0.5
        np.testing.assert_allclose(np.c_[u, v], project(scene.K, pose, scene.points), atol=1e-9)


def test_opengl_camera_to_world_converts_back_to_the_same_pose():
    scene = make_scene(num_cameras=3, num_points=10, seed=2)
    for pose in scene.poses:
        back = opengl_c2w_to_opencv_pose(opencv_pose_to_opengl_c2w(pose))
        np.testing.assert_allclose(back.R, pose.R, atol=1e-12)
        np.testing.assert_allclose(back.t, pose.t, atol=1e-12)


def test_json_writer_accepts_numpy_values(tmp_path):
    write_json(tmp_path / "r.json", {"a": np.arange(3), "b": np.float32(1.5), "c": np.int64(2)})
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": [0, 1, 2], "b": 1.5, "c": 2}
