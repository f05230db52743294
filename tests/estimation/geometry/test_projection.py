"""The one camera model and projection: COLMAP's models, OpenCV's distortion, pixel <-> normalized."""

import cv2
import numpy as np
import pytest

from estimation.geometry.projection import (
    COLMAP_MODEL_NAMES,
    Camera,
    Observations,
    ideal_pixels,
    normalized_to_pixel,
    observation_cameras,
    pixel_to_normalized,
    project,
    reprojection_residuals,
)
from estimation.synthetic import rotation_about_axis

CAMERAS = {
    "pinhole": Camera("pinhole", fx=800.0, fy=790.0, cx=400.0, cy=300.0),
    "simple-radial": Camera("simple-radial", fx=800.0, fy=800.0, cx=401.0, cy=299.0, k1=-0.12),
    "radial": Camera("radial", fx=700.0, fy=700.0, cx=395.0, cy=305.0, k1=0.08, k2=-0.03),
    "opencv": Camera("opencv", fx=810.0, fy=805.0, cx=402.0, cy=297.0, k1=-0.2, k2=0.05, p1=1e-3, p2=-2e-3),
}


def random_scene(seed=0, num=400):
    rng = np.random.default_rng(seed)
    R = rotation_about_axis(rng.normal(size=3), 0.3)
    t = np.array([0.1, -0.2, 0.5])
    x_cam = np.column_stack([rng.uniform(-0.45, 0.45, (num, 2)), np.ones(num)]) * rng.uniform(2, 6, (num, 1))
    return R, t, (x_cam - t) @ R      # world points X with R X + t = x_cam


@pytest.mark.parametrize("model", list(CAMERAS))
def test_projection_matches_opencv_project_points(model):
    camera = CAMERAS[model]
    R, t, points = random_scene()
    ours = project(camera, R, t, points).uv
    theirs, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, camera.K, camera.distortion)
    np.testing.assert_allclose(ours, theirs[:, 0], atol=1e-8)


@pytest.mark.parametrize("model", list(CAMERAS))
def test_pixel_to_normalized_recovers_the_ray_of_a_projected_point(model):
    camera = CAMERAS[model]
    R, t, points = random_scene(seed=1)
    uv = project(camera, R, t, points).uv
    x_cam = points @ R.T + t
    np.testing.assert_allclose(pixel_to_normalized(camera, uv), x_cam[:, :2] / x_cam[:, 2:], atol=1e-10)
    np.testing.assert_allclose(normalized_to_pixel(camera, pixel_to_normalized(camera, uv)), uv, atol=1e-8)


def test_undistortion_agrees_with_opencv():
    camera = CAMERAS["opencv"]
    uv = np.random.default_rng(2).uniform([50, 40], [750, 560], (300, 2))
    theirs = cv2.undistortPoints(uv[:, None], camera.K, camera.distortion,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14))[:, 0]
    np.testing.assert_allclose(pixel_to_normalized(camera, uv), theirs, atol=1e-9)


def test_ideal_pixels_are_what_the_distortion_free_camera_sees():
    camera = CAMERAS["radial"]
    R, t, points = random_scene(seed=3)
    uv = project(camera, R, t, points).uv
    ideal = project(camera.pinhole(), R, t, points).uv
    np.testing.assert_allclose(ideal_pixels(camera, uv), ideal, atol=1e-8)


def test_per_point_cameras_project_each_point_with_its_own_intrinsics():
    cameras = [CAMERAS["opencv"], Camera("opencv", fx=500.0, fy=505.0, cx=320.0, cy=240.0, k1=0.1)]
    R, t, points = random_scene(seed=4, num=10)
    index = np.arange(10) % 2
    together = project(Camera.take(cameras, index), R, t, points).uv
    for c, camera in enumerate(cameras):
        np.testing.assert_allclose(together[index == c], project(camera, R, t, points[index == c]).uv)


def test_taking_one_shared_camera_gives_per_point_arrays_of_its_values():
    camera = CAMERAS["opencv"]
    taken = Camera.take([camera] * 4, np.array([3, 0, 0, 2, 1]))
    for field in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "skew"):
        np.testing.assert_array_equal(getattr(taken, field), np.full(5, getattr(camera, field)))
    assert taken.model == "opencv"


def test_observation_cameras_are_the_shared_camera_itself_or_taken_per_element():
    shared = CAMERAS["opencv"]
    assert observation_cameras([shared] * 3, np.array([2, 0, 1])) is shared
    # Equal but distinct objects are taken per element.
    cameras = [shared, Camera("opencv", fx=500.0, fy=505.0, cx=320.0, cy=240.0, k1=0.1)]
    index = np.array([1, 0, 1])
    taken = observation_cameras(cameras, index)
    np.testing.assert_array_equal(taken.fx, Camera.take(cameras, index).fx)


def test_a_shared_camera_projects_bitwise_as_its_per_point_arrays():
    camera = CAMERAS["opencv"]
    R, t, points = random_scene(seed=6, num=50)
    taken = Camera.take([camera] * 2, np.zeros(50, np.int64))
    np.testing.assert_array_equal(project(camera, R, t, points).uv, project(taken, R, t, points).uv)
    np.testing.assert_array_equal(ideal_pixels(camera, points[:, :2]), ideal_pixels(taken, points[:, :2]))


def test_reprojection_residuals_accept_a_3x3_K_as_the_pinhole_camera():
    camera = CAMERAS["pinhole"]
    R, t, points = random_scene(seed=5, num=20)
    uv = project(camera, R, t, points).uv + 1.0
    obs = Observations(R=np.broadcast_to(R, (20, 3, 3)), t=np.broadcast_to(t, (20, 3)), uv=uv,
                       point_index=np.arange(20), num_points=20)
    np.testing.assert_allclose(reprojection_residuals(camera.K, obs, points), -1.0, atol=1e-9)
    np.testing.assert_allclose(reprojection_residuals(camera, obs, points), -1.0, atol=1e-9)


@pytest.mark.parametrize("model", list(CAMERAS))
def test_colmap_parameters_round_trip_in_colmaps_order(model):
    camera = CAMERAS[model]
    params = camera.colmap_params()
    assert len(params) == {"pinhole": 4, "simple-radial": 4, "radial": 5, "opencv": 8}[model]
    assert Camera.from_colmap(COLMAP_MODEL_NAMES[model], params) == camera


def test_a_model_rejects_coefficients_it_does_not_have():
    with pytest.raises(ValueError, match="simple-radial has no k2"):
        Camera("simple-radial", fx=1.0, fy=1.0, cx=0.0, cy=0.0, k2=0.1)
    assert Camera.from_K(np.eye(3)).as_model("radial").model == "radial"
