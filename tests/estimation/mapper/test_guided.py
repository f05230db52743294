"""Guided 2D-3D matching: an image whose tracks reach too few of the model's points is matched against the
points its failed pose projects near its keypoints, and registered at its true pose."""

import dataclasses

import numpy as np

from estimation.config import ReconstructionConfig
from estimation.features.sift import ImageFeatures, TrackFeatures, root_sift
from estimation.geometry.alignment import aligned_pose_errors
from estimation.mapper.guided import guided_matches
from estimation.mapper.incremental import reconstruct_models
from estimation.synthetic import make_scene

KEYPOINT_SIZE_PX = 2.0
"""Every synthetic keypoint at the finest scale (the final BA weighs its observations alike)."""

RADIUS, RATIO, MAX_DISTANCE = 8.0, 0.8, 0.7


def unit_rows(rng, count):
    return root_sift(rng.integers(0, 60, (count, 128)))


def test_a_keypoint_matches_its_nearest_point_in_view_when_the_prediction_puts_the_point_near_it():
    rng = np.random.default_rng(0)
    points = unit_rows(rng, 4)
    projected = np.array([[100.0, 100.0], [104.0, 100.0], [300.0, 300.0], [500.0, 500.0]])
    keypoints_uv = np.array([[101.0, 99.0], [300.0, 330.0], [502.0, 501.0]])
    keypoints = np.vstack([points[0], points[2], points[3]])

    matches = guided_matches(projected, np.arange(len(points)), points, keypoints_uv, keypoints, RADIUS,
                             RATIO, MAX_DISTANCE)

    # Keypoint 1 has point 2's descriptor but lies 30 px from its predicted place.
    assert matches.keypoints.tolist() == [0, 2] and matches.points.tolist() == [0, 3]
    assert np.allclose(matches.distances, 0.0, atol=1e-3)


def test_a_repeated_texture_fails_the_ratio_test_over_the_view_and_a_point_keeps_its_closest_keypoint():
    rng = np.random.default_rng(1)
    points = unit_rows(rng, 3)
    points[1] = points[0]                       # the same texture twice, far apart in the view
    projected = np.array([[100.0, 100.0], [400.0, 100.0], [300.0, 300.0]])
    noisy = points[2] + 0.05 * unit_rows(rng, 1)[0]
    keypoints_uv = np.array([[101.0, 100.0], [300.0, 301.0], [302.0, 300.0]])
    keypoints = np.vstack([points[0], points[2], noisy / np.linalg.norm(noisy)])

    matches = guided_matches(projected, np.arange(len(points)), points, keypoints_uv, keypoints, RADIUS,
                             RATIO, MAX_DISTANCE)

    # Keypoint 0 is as close to points 0 and 1: refused, though only point 0 is predicted near it.
    # Point 2 keeps keypoint 1 (the exact descriptor), not keypoint 2.
    assert matches.keypoints.tolist() == [1] and matches.points.tolist() == [2]


def scene_with_a_weakly_tracked_image(image: int, kept: int, seed: int = 3):
    """A synthetic scene whose image `image` keeps only `kept` of its track observations (its pairwise
    matches found few), while its keypoints see every point; every point has its own SIFT descriptor, each
    observation a noisy copy of it."""
    scene = make_scene(num_cameras=6, num_points=400, noise_px=0.5, seed=seed)
    tracks, rng = scene.tracks, np.random.default_rng(seed)
    point_sift = rng.integers(0, 60, (tracks.num_tracks, 128))
    images = []
    rank = np.zeros(len(tracks.track_index), np.int64)
    for m in range(len(tracks.image_names)):
        in_image = np.flatnonzero(tracks.image_index == m)
        rank[in_image] = np.arange(len(in_image))
        noise = rng.integers(-3, 4, (len(in_image), 128))
        images.append(ImageFeatures(tracks.uv[in_image],
                                    np.clip(point_sift[tracks.track_index[in_image]] + noise, 0, 255)
                                    .astype(np.uint8), np.full(len(in_image), KEYPOINT_SIZE_PX)))
    in_weak = np.flatnonzero(tracks.image_index == image)
    keep = np.ones(len(tracks.track_index), bool)
    keep[in_weak[kept:]] = False
    weak_tracks = dataclasses.replace(tracks, track_index=tracks.track_index[keep],
                                      image_index=tracks.image_index[keep], uv=tracks.uv[keep])
    return scene, weak_tracks, TrackFeatures(images, rank[keep])


def test_an_image_with_too_few_track_correspondences_registers_by_guided_matching_at_its_true_pose():
    scene, tracks, keypoints = scene_with_a_weakly_tracked_image(image=4, kept=10)
    config = ReconstructionConfig()

    without = reconstruct_models(tracks, scene.K, config)[0]
    assert 4 not in without.poses and "inliers among 10" in without.unregistered[4]

    model = reconstruct_models(tracks, scene.K, config, keypoints=keypoints)[0]
    assert sorted(model.poses) == list(range(6))
    assert model.stats.guided_registrations["5.png"] > 300
    registered = sorted(model.poses)
    errors = aligned_pose_errors([model.poses[m] for m in registered], [scene.poses[m] for m in registered])
    assert errors.rotation_deg.max() < 0.2

    unguided = config.mapper.model_copy(update={"guided_matching": False})
    assert 4 not in reconstruct_models(tracks, scene.K, config.model_copy(update={"mapper": unguided}),
                                    keypoints=keypoints)[0].poses


def test_a_registration_that_guided_matching_barely_adds_to_is_refused_with_the_reason():
    """Image 5.png sees only 2 points beyond its 10 tracks: 12 inliers would pass the floor, but a pose
    resting on 2 new matches is little more than a second RANSAC draw (guided_min_inliers)."""
    scene, tracks, keypoints = scene_with_a_weakly_tracked_image(image=4, kept=10)
    few = keypoints.images[4]
    keypoints.images[4] = type(few)(few.uv[:12], few.sift[:12], few.size[:12])

    model = reconstruct_models(tracks, scene.K, ReconstructionConfig(), keypoints=keypoints)[0]

    assert 4 not in model.poses
    assert "2 guided 2D-3D matches: 2 of its inliers are guided matches (need 4)" in model.unregistered[4]
