"""The synthetic ground truth itself: geometry, noise, outliers, visibility, similarity alignment, and the
rendered box ring."""

import numpy as np
import pytest

from estimation.geometry.alignment import (
    Similarity,
    align_similarity,
    aligned_pose_errors,
    relative_rotation_errors_deg,
    rotation_angle_deg,
    rotation_angles_deg,
)
from estimation.synthetic import (
    BACKGROUND_GREY,
    BOX_HALF_SIZE,
    make_scene,
    project,
    render_box_ring,
    rotation_about_axis,
)
from estimation.types import CameraPose


def test_every_point_is_in_front_of_every_camera_and_inside_every_image():
    scene = make_scene(num_cameras=8, num_points=300, seed=3)
    for pose in scene.poses:
        depth = (scene.points @ pose.R.T + pose.t)[:, 2]
        uv = project(scene.K, pose, scene.points)
        assert depth.min() > 0
        assert (uv >= 0).all() and (uv[:, 0] < scene.width).all() and (uv[:, 1] < scene.height).all()


def test_poses_are_proper_rotations():
    for pose in make_scene(num_cameras=40, seed=1).poses:
        np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(pose.R) == pytest.approx(1.0)


def test_noise_free_tracks_are_exact_projections():
    scene = make_scene(num_points=50)
    t = scene.tracks
    for o in range(len(t.track_index)):
        expected = project(scene.K, scene.poses[t.image_index[o]], scene.points[t.track_index[o]][None])[0]
        np.testing.assert_allclose(t.uv[o], expected, atol=1e-9)


def test_noise_has_the_requested_standard_deviation():
    clean, noisy = make_scene(num_points=2000, seed=4), make_scene(num_points=2000, noise_px=0.5, seed=4)
    assert np.std(noisy.tracks.uv - clean.tracks.uv) == pytest.approx(0.5, rel=0.05)


def test_outliers_replace_the_requested_fraction_of_observations_by_far_away_pixels():
    clean = make_scene(num_points=1000, seed=5)
    dirty = make_scene(num_points=1000, outlier_fraction=0.3, seed=5)
    assert (~dirty.inlier_mask).mean() == pytest.approx(0.3, abs=1e-3)
    moved = np.linalg.norm(dirty.tracks.uv - clean.tracks.uv, axis=1)
    assert np.all(moved[dirty.inlier_mask] == 0)
    assert np.median(moved[~dirty.inlier_mask]) > 50


def test_partial_visibility_keeps_at_least_two_observations_per_track():
    scene = make_scene(num_cameras=6, num_points=1000, visibility=0.3, seed=6)
    counts = np.bincount(scene.tracks.track_index, minlength=1000)
    assert counts.min() >= 2
    assert counts.mean() < 6 * 0.5
    pairs = np.stack([scene.tracks.track_index, scene.tracks.image_index], axis=1)
    assert len(np.unique(pairs, axis=0)) == len(pairs), "a track appears at most once per image"


def test_same_seed_gives_the_same_scene():
    a = make_scene(noise_px=1.0, outlier_fraction=0.2, seed=9)
    b = make_scene(noise_px=1.0, outlier_fraction=0.2, seed=9)
    np.testing.assert_array_equal(a.tracks.uv, b.tracks.uv)


def test_align_similarity_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(20, 3))
    R = rotation_about_axis(np.array([1.0, 2.0, 3.0]), 0.7)
    target = 2.5 * source @ R.T + np.array([1.0, -2.0, 0.5])
    similarity = align_similarity(source, target)
    assert similarity.scale == pytest.approx(2.5)
    np.testing.assert_allclose(similarity.R, R, atol=1e-12)
    np.testing.assert_allclose(similarity.apply_points(source), target, atol=1e-12)


def test_aligned_pose_errors_vanish_for_a_similarity_transformed_reconstruction():
    scene = make_scene()
    R = rotation_about_axis(np.array([0.3, -1.0, 0.2]), 2.0)
    moved = [Similarity(0.3, R, np.array([5.0, 1.0, 2.0])).apply_pose(p) for p in scene.poses]
    errors = aligned_pose_errors(moved, scene.poses)
    assert errors.rotation_deg.max() < 1e-9
    assert errors.center.max() < 1e-9


def test_relative_rotation_errors_ignore_the_frame_and_blame_the_pairs_of_a_turned_camera():
    scene = make_scene(num_cameras=5)
    R = rotation_about_axis(np.array([0.3, -1.0, 0.2]), 2.0)
    moved = [Similarity(0.3, R, np.array([5.0, 1.0, 2.0])).apply_pose(p) for p in scene.poses]
    assert relative_rotation_errors_deg(moved, scene.poses).max() < 1e-9
    turned = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(2.0)) @ moved[3].R
    moved[3] = CameraPose(turned, moved[3].t)
    errors = relative_rotation_errors_deg(moved, scene.poses)   # pairs (0,1) (0,2) (0,3) (0,4) (1,2) ...
    assert len(errors) == 10
    assert errors[[2, 5, 7, 9]] == pytest.approx(2.0, abs=1e-9)   # every pair with camera 3
    assert np.delete(errors, [2, 5, 7, 9]).max() < 1e-9


def test_relative_rotation_errors_refuse_pose_lists_of_different_lengths():
    scene = make_scene(num_cameras=5)
    with pytest.raises(ValueError, match="4 estimated poses against 5 true ones"):
        relative_rotation_errors_deg(scene.poses[:4], scene.poses)


def test_rotation_angle_is_accurate_for_tiny_angles():
    assert rotation_angle_deg(np.eye(3), rotation_about_axis(np.array([0, 0, 1.0]), 1e-9)) == pytest.approx(
        np.degrees(1e-9), rel=1e-6)


def test_rotation_angles_of_stacked_rotations_are_each_pairs_angle_up_to_a_half_turn():
    axis = np.array([0.2, -1.0, 0.4])
    angles = np.array([0.0, 0.3, 2.0, np.pi])
    turned = np.stack([rotation_about_axis(axis, angle) for angle in angles])
    start = rotation_about_axis(np.array([1.0, 0.0, 0.0]), 0.7)
    assert rotation_angles_deg(start, start @ turned) == pytest.approx(np.degrees(angles), abs=1e-9)
    assert rotation_angle_deg(start, start @ turned[2]) == pytest.approx(np.degrees(2.0))


def test_the_rendered_box_is_where_its_true_cameras_project_it_and_the_ground_around_it():
    ring = render_box_ring(num_views=4, size=64, seed=1)
    assert len(ring.images) == len(ring.poses) == 4
    for image, pose in zip(ring.images, ring.poses, strict=True):
        assert image.shape == (64, 64, 3) and image.dtype == np.uint8
        u, v = project(ring.K, pose, np.array([[0.0, 0.0, BOX_HALF_SIZE[2]]]))[0]   # the top's centre
        top = image[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2]
        assert np.abs(top.astype(float) - BACKGROUND_GREY).max() > 5    # the box, not the plain sky
        below = image[-4:].reshape(-1, 3).astype(float)
        assert below.std(axis=0).max() > 5                              # the ground's marks, not flat grey


def test_views_half_a_turn_apart_look_more_alike_than_views_a_quarter_turn_apart():
    ring = render_box_ring(num_views=4, size=96, textured_ground=False, unique_marks=0, seed=2)
    first, quarter, half = (ring.images[k].astype(float) for k in (0, 1, 2))
    assert np.abs(first - half).mean() < 0.8 * np.abs(first - quarter).mean()


@pytest.mark.parametrize(("field", "value"), [("num_views", 2), ("size", 8)])
def test_a_box_ring_too_small_to_render_is_refused_naming_its_argument(field, value):
    with pytest.raises(ValueError, match=f"{field} must be at least .*, got {value}"):
        render_box_ring(**{field: value})
