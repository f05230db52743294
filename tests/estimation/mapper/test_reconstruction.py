"""The Reconstruction's named operations: points, observations, track completion and merging, filtering."""

import dataclasses

import numpy as np
import pytest

from estimation.geometry.projection import Camera, observation_cameras
from estimation.mapper.reconstruction import Reconstruction, pixel_noise_sigma
from estimation.synthetic import make_scene


@pytest.fixture()
def posed():
    """A Reconstruction over a noise-free 5-image scene with every image registered at its true pose."""
    truth = make_scene(num_points=50, seed=21)
    scene = Reconstruction(truth.tracks, truth.K)
    for m, pose in enumerate(truth.poses):
        scene.register_image(m, pose)
    return truth, scene


def observations_of_track(truth, track):
    return np.flatnonzero(truth.tracks.track_index == track)


def test_a_point_owns_its_observations_and_vanishes_below_two(posed):
    truth, scene = posed
    obs = observations_of_track(truth, 0)[:3]
    [point] = scene.add_points(truth.points[[0]], obs, np.zeros(3, int))
    assert scene.num_points == 1 and list(scene.obs_point[obs]) == [point] * 3
    np.testing.assert_allclose(scene.errors(obs), 0.0, atol=1e-9)
    scene.remove_observations(obs[:1])
    assert scene.num_points == 1 and scene.obs_point[obs[0]] == -1
    scene.remove_observations(obs[1:2])
    assert scene.num_points == 0 and np.all(scene.obs_point[obs] == -1)


def test_an_observation_joins_only_a_live_point_of_its_own_track(posed):
    truth, scene = posed
    [point] = scene.add_points(truth.points[[0]], observations_of_track(truth, 0)[:2], np.zeros(2, int))
    with pytest.raises(ValueError, match="its own track"):
        scene.add_observations(observations_of_track(truth, 1)[:1], [point])
    with pytest.raises(ValueError, match="already supports"):
        scene.add_observations(observations_of_track(truth, 0)[:1], [point])
    scene.add_observations(observations_of_track(truth, 0)[2:3], [point])
    assert scene.point_observation_counts()[point] == 3


def test_complete_tracks_continues_points_into_registered_images_within_the_threshold(posed):
    truth, scene = posed
    obs = np.concatenate([observations_of_track(truth, t)[:2] for t in range(10)])
    scene.add_points(truth.points[:10], obs, np.repeat(np.arange(10), 2))
    added = scene.complete_tracks(max_error_px=1.0)
    assert added == 10 * 3
    assert np.all(scene.point_observation_counts()[:10] == 5)


def test_deregistering_an_image_drops_its_observations(posed):
    truth, scene = posed
    obs = observations_of_track(truth, 0)
    scene.add_points(truth.points[[0]], obs, np.zeros(5, int))
    scene.deregister_image(4)
    assert not scene.registered[4] and 4 not in scene.order
    assert scene.point_observation_counts()[0] == 4


def test_merge_tracks_joins_the_two_points_of_a_split_track(posed):
    truth, scene = posed
    obs = observations_of_track(truth, 3)
    scene.add_points(np.stack([truth.points[3] + 0.01, truth.points[3] - 0.01]), obs[:4],
                     np.array([0, 0, 1, 1]))
    assert scene.merge_tracks(max_error_px=1.0) == 1
    assert scene.num_points == 1
    [point] = np.flatnonzero(scene.point_alive)
    np.testing.assert_allclose(scene.point_xyz[point], truth.points[3], atol=1e-6)
    assert scene.point_observation_counts()[point] == 4


def test_filter_points_drops_far_observations_and_narrow_points(posed):
    truth, scene = posed
    obs = observations_of_track(truth, 5)
    [point] = scene.add_points(truth.points[[5]] + [0.0, 0.0, 0.3], obs, np.zeros(5, int))
    removed = scene.filter_points(max_error_px=1.0, min_angle_deg=1.0)
    assert removed == 5 and scene.num_points == 0
    obs = observations_of_track(truth, 6)
    scene.add_points(truth.points[[6]], obs, np.zeros(5, int))
    assert scene.filter_points(max_error_px=1.0, min_angle_deg=179.0) == 5    # no two rays that wide


def test_filter_points_holds_each_observation_to_the_limit_times_its_relative_sigma_under_a_ceiling():
    truth = make_scene(num_points=50, seed=21)
    obs = observations_of_track(truth, 5)
    shifted = truth.tracks.uv.copy()
    shifted[obs] += [1.5, 0.0]                                  # every observation of track 5 1.5 px off
    relative_sigma = np.ones(len(shifted))

    def filtered(sigma_of_track: float, ceiling_px: float = np.inf) -> int:
        scene = Reconstruction(dataclasses.replace(truth.tracks, uv=shifted), truth.K)
        for m, pose in enumerate(truth.poses):
            scene.register_image(m, pose)
        scene.add_points(truth.points[[5]], obs, np.zeros(len(obs), int))
        relative_sigma[obs] = sigma_of_track
        return scene.filter_points(1.0, 1.0, relative_sigma=relative_sigma, ceiling_px=ceiling_px)

    assert filtered(1.0) == len(obs)                            # beyond 1 px
    assert filtered(2.0) == 0                                   # within 2 x 1 px
    assert filtered(8.0, ceiling_px=1.2) == len(obs)            # never beyond the ceiling


def test_triangulate_tracks_keeps_the_consistent_observations_of_tracks_with_outliers():
    truth = make_scene(num_points=200, noise_px=0.3, outlier_fraction=0.2, seed=22)
    scene = Reconstruction(truth.tracks, truth.K)
    for m, pose in enumerate(truth.poses):
        scene.register_image(m, pose)
    added = scene.triangulate_tracks(np.arange(200), max_error_px=2.0, min_angle_deg=1.0,
                                     hypotheses_per_point=8)
    assert added >= 195
    used = scene.used_observations()
    assert np.mean(truth.inlier_mask[used]) > 0.99
    assert np.mean(scene.obs_point[truth.inlier_mask] >= 0) > 0.97
    alive = np.flatnonzero(scene.point_alive)
    errors = np.linalg.norm(scene.point_xyz[alive] - truth.points[scene.point_track[alive]], axis=1)
    assert np.median(errors) < 0.01


def test_pixel_noise_sigma_is_the_median_of_rayleigh_residuals_barely_moved_by_outliers():
    rng = np.random.default_rng(3)
    sigma = 0.4
    errors = np.linalg.norm(rng.normal(0.0, sigma, (20000, 2)), axis=1)
    errors[:2000] = rng.uniform(0.0, 4.0, 2000)                         # 10 % outliers up to 4 px
    assert pixel_noise_sigma(errors, np.ones(len(errors))) == pytest.approx(sigma, rel=0.1)
    # Residuals of points fitted to two observations are half as large: the variance factors say so.
    assert pixel_noise_sigma(0.5 * errors[2000:], np.full(18000, 0.25)) == pytest.approx(sigma, rel=0.02)
    assert np.isnan(pixel_noise_sigma(np.zeros(0), np.zeros(0)))


def test_noise_sigma_is_measured_on_used_and_free_observations_within_the_limit(posed):
    truth, scene = posed
    rng = np.random.default_rng(4)
    for track in range(50):
        obs = observations_of_track(truth, track)
        scene.add_points(truth.points[[track]], obs[:4], np.zeros(4, int))     # the 5th stays free
    scene.tracks = dataclasses.replace(scene.tracks, uv=scene.tracks.uv + rng.normal(0.0, 0.3, (250, 2)))
    scene.observed_uv = scene.tracks.uv
    sigma = scene.noise_sigma(max_error_px=4.0)
    assert 0.2 < sigma < 0.45                       # 250 samples of a 0.3 px noise (points not refitted)
    assert scene.noise_sigma(max_error_px=1e-6) != scene.noise_sigma(max_error_px=4.0)


def test_errors_of_a_shared_camera_equal_those_of_the_same_camera_given_per_image():
    truth = make_scene(num_points=50, seed=21)
    camera = Camera.from_K(truth.K, "simple-radial", k1=0.05)
    shared = Reconstruction(truth.tracks, camera)
    per_image = Reconstruction(truth.tracks, [dataclasses.replace(camera) for _ in truth.poses])
    obs = np.concatenate([observations_of_track(truth, t) for t in range(10)])
    images = truth.tracks.image_index[obs]
    assert observation_cameras(shared.cameras, images) is camera               # used as is
    assert observation_cameras(per_image.cameras, images).fx.shape == images.shape
    for scene in (shared, per_image):
        for m, pose in enumerate(truth.poses):
            scene.register_image(m, pose)
        scene.add_points(truth.points[:10] + 0.01, obs, truth.tracks.track_index[obs])
    np.testing.assert_array_equal(shared.errors(obs), per_image.errors(obs))
    assert np.all(shared.errors(obs) > 0)


def test_points_seen_in_marks_the_points_observed_in_any_of_the_images(posed):
    truth, scene = posed
    track_0, track_1 = observations_of_track(truth, 0), observations_of_track(truth, 1)
    in_image_0 = track_0[truth.tracks.image_index[track_0] != 4]      # seen in images 0-3
    in_image_4 = track_1[truth.tracks.image_index[track_1] != 0]      # seen in images 1-4
    first, second = scene.add_points(truth.points[:2], np.concatenate([in_image_0, in_image_4]),
                                     np.repeat([0, 1], [len(in_image_0), len(in_image_4)]))
    assert list(np.flatnonzero(scene.points_seen_in([0]))) == [first]
    assert list(np.flatnonzero(scene.points_seen_in([4]))) == [second]
    assert list(np.flatnonzero(scene.points_seen_in([0, 4]))) == [first, second]
    assert list(np.flatnonzero(scene.points_seen_in([1]))) == [first, second]
