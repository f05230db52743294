"""Bundle adjustment against synthetic ground truth: convergence, gauge, robustness, local BA, bad input."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from estimation.bundle_adjustment.factor_graph import (
    IntrinsicsRefinement,
    _covariance_of,
    _marked,
    _pinhole_calibration,
    bundle_adjust,
    camera_pose_from_gtsam,
    camera_pose_to_gtsam,
    camera_to_gtsam,
    huber_cost,
    noise_levels,
    reprojection_residuals,
    rms,
)
from estimation.config import BundleAdjustmentConfig
from estimation.errors import InputError
from estimation.geometry.alignment import align_similarity, aligned_pose_errors
from estimation.geometry.projection import Camera
from estimation.synthetic import make_scene, project
from estimation.types import CameraPose


def perturbed(poses, points, rng, rotation_rad=0.02, center=0.1, point=0.05, keep=(0,)):
    """Poses (except `keep`) and points moved by random rotations / offsets of the given sizes."""
    moved = [
        pose
        if k in keep
        else CameraPose.from_center(
            gtsam.Rot3.Expmap(rng.normal(0, rotation_rad, 3)).matrix() @ pose.R,
            pose.center + rng.normal(0, center, 3),
        )
        for k, pose in enumerate(poses)
    ]
    return moved, points + rng.normal(0, point, points.shape)


def observations(scene):
    return scene.tracks.image_index, scene.tracks.track_index, scene.tracks.uv


def run(scene, poses, points, config=None, **kwargs):
    return bundle_adjust(
        scene.K, poses, points, *observations(scene), config or BundleAdjustmentConfig(), **kwargs
    )


def test_pose_conversion_to_gtsam_is_camera_to_world_and_round_trips():
    scene = make_scene(num_cameras=3, num_points=20, seed=4)
    pose = scene.poses[1]
    pose3 = camera_pose_to_gtsam(pose)
    np.testing.assert_allclose(pose3.translation(), pose.center, atol=1e-12)
    back = camera_pose_from_gtsam(pose3)
    np.testing.assert_allclose(back.R, pose.R, atol=1e-12)
    np.testing.assert_allclose(back.t, pose.t, atol=1e-12)
    camera = gtsam.PinholeCameraCal3_S2(pose3, gtsam.Cal3_S2(*scene.K[[0, 1, 0, 0, 1], [0, 1, 1, 2, 2]]))
    ours = reprojection_residuals(
        scene.K, [pose], scene.points[:1], np.array([0]), np.array([0]), np.zeros((1, 2))
    )
    np.testing.assert_allclose(camera.project(scene.points[0]), ours[0], atol=1e-9)


def test_huber_cost_is_gtsams_robust_factor_error():
    config = BundleAdjustmentConfig(huber_threshold_px=2.0, measurement_sigma_px=0.5)
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.huber_threshold_px / config.measurement_sigma_px),
        gtsam.noiseModel.Isotropic.Sigma(2, config.measurement_sigma_px),
    )
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3())
    values.insert(1, np.array([0.1, -0.2, 4.0]))
    calibration = gtsam.Cal3_S2(500, 500, 0, 320, 240)
    projected = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(), calibration).project(np.array([0.1, -0.2, 4.0]))
    for offset in ([0.3, -0.4], [3.0, 4.0]):  # inside and beyond the Huber threshold
        factor = gtsam.GenericProjectionFactorCal3_S2(projected + offset, noise, 0, 1, calibration)
        ours = huber_cost(np.array([offset]), config.huber_threshold_px, config.measurement_sigma_px)
        assert factor.error(values) == pytest.approx(ours, rel=1e-9)


def test_noise_free_scene_is_recovered_exactly_after_similarity_alignment():
    scene = make_scene(num_cameras=5, num_points=200, seed=1)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(0))
    result = run(scene, poses, points, BundleAdjustmentConfig(relative_error_tol=1e-12, max_iterations=50))
    errors = aligned_pose_errors(result.poses, scene.poses)
    assert errors.rotation_deg.max() < 1e-6
    assert errors.center.max() < 1e-6 * scene.scene_size
    assert result.final_rms_px < 1e-6 < 1.0 < result.initial_rms_px


def test_the_error_figures_are_of_the_inputs_as_passed_even_when_the_caller_changes_them_later():
    scene = make_scene(num_cameras=4, num_points=100, noise_px=0.5, seed=3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    image_index, track_index, uv = (array.copy() for array in observations(scene))
    config = BundleAdjustmentConfig()
    result = bundle_adjust(scene.K, poses, points, image_index, track_index, uv, config)
    before = reprojection_residuals(scene.K, poses, points, image_index, track_index, uv)
    after = reprojection_residuals(scene.K, result.poses, result.points, image_index, track_index, uv)
    for array in (points, image_index, track_index, uv):   # read lazily: the call's copies stay
        array[...] = 0
    assert result.initial_rms_px == rms(before) and result.final_rms_px == rms(after)
    assert result.initial_cost == huber_cost(before, config.huber_threshold_px, config.measurement_sigma_px)
    assert result.final_cost == huber_cost(after, config.huber_threshold_px, config.measurement_sigma_px)


def test_perturbed_noisy_scene_converges_to_truth_and_noise_level():
    scene = make_scene(num_cameras=6, num_points=400, noise_px=0.5, seed=2)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(1))
    result = run(scene, poses, points)

    errors = aligned_pose_errors(result.poses, scene.poses)
    assert errors.rotation_deg.max() < 0.05
    assert errors.center.max() < 1e-3 * scene.scene_size
    similarity = align_similarity(
        np.array([p.center for p in result.poses]), np.array([p.center for p in scene.poses])
    )
    point_errors = np.linalg.norm(similarity.apply_points(result.points) - scene.points, axis=1)
    assert np.median(point_errors) < 2e-3 * scene.scene_size
    # Least squares leaves residuals of the noise level shrunk by the fitted degrees of freedom:
    # E[rms^2] = rms_truth^2 (1 - dof / #residuals), dof = 6 per free camera + 3 per point - 1 (scale).
    rms_at_truth = rms(reprojection_residuals(scene.K, scene.poses, scene.points, *observations(scene)))
    dof = 6 * (len(scene.poses) - 1) + 3 * len(scene.points) - 1
    expected = rms_at_truth * np.sqrt(1 - dof / (2 * len(scene.tracks.uv)))
    assert result.final_rms_px == pytest.approx(expected, rel=0.03)
    assert result.initial_rms_px > 10 * result.final_rms_px
    assert result.final_cost < result.initial_cost
    assert result.iterations >= 1


@pytest.mark.parametrize(
    ("ordering", "linear_solver"),
    [
        ("colamd", "multifrontal_cholesky"),
        ("metis", "sequential_cholesky"),
        ("points_first", "multifrontal_qr"),
    ],
)
def test_every_ordering_and_linear_solver_reaches_the_same_optimum(ordering, linear_solver):
    scene = make_scene(num_cameras=4, num_points=150, noise_px=0.5, seed=3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    reference = run(scene, poses, points, BundleAdjustmentConfig(relative_error_tol=1e-10))
    other = run(
        scene,
        poses,
        points,
        BundleAdjustmentConfig(relative_error_tol=1e-10, ordering=ordering, linear_solver=linear_solver),
    )
    assert other.final_cost == pytest.approx(reference.final_cost, rel=1e-6)
    np.testing.assert_allclose(other.points, reference.points, atol=1e-6)


def test_block_jacobi_pcg_reaches_the_direct_solvers_cost_within_a_thousandth():
    scene = make_scene(num_cameras=4, num_points=150, noise_px=0.5, seed=3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    direct = run(scene, poses, points)
    iterative = run(scene, poses, points, BundleAdjustmentConfig(linear_solver="pcg_block_jacobi"))
    assert iterative.final_cost < 0.01 * iterative.initial_cost
    assert iterative.final_cost == pytest.approx(direct.final_cost, rel=1e-3)


def test_gauss_newton_reaches_levenberg_marquardts_optimum_from_a_near_start():
    scene = make_scene(num_cameras=4, num_points=150, noise_px=0.5, seed=3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    marquardt = run(scene, poses, points, BundleAdjustmentConfig(relative_error_tol=1e-10))
    newton = run(scene, poses, points,
                 BundleAdjustmentConfig(relative_error_tol=1e-10, optimizer="gauss_newton"))
    assert newton.final_cost == pytest.approx(marquardt.final_cost, rel=1e-9)
    np.testing.assert_allclose(newton.points, marquardt.points, atol=1e-6)


def test_gauss_newton_whose_step_raises_the_cost_falls_back_to_levenberg_marquardt(monkeypatch):
    # From this far (0.3 rad, a unit off) the first undamped step overshoots: GTSAM's Gauss-Newton stops
    # there at ten times the initial cost.
    scene = make_scene(num_cameras=4, num_points=100, noise_px=0.5, seed=0)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(0), 0.3, 1.0, 1.0)
    marquardt = run(scene, poses, points)
    calls = []
    result = run(scene, poses, points, BundleAdjustmentConfig(optimizer="gauss_newton"),
                 on_iteration=lambda iteration, error: calls.append((iteration, error)))
    assert result.final_cost == pytest.approx(marquardt.final_cost, rel=1e-12)
    assert result.final_cost < 1e-3 * result.initial_cost
    # The hook sees the iterations of the run that gave the result only.
    assert [iteration for iteration, _ in calls] == list(range(1, result.iterations + 1))
    assert result.iterations == marquardt.iterations


def test_gauss_newton_on_an_indeterminate_system_falls_back_to_levenberg_marquardt():
    # Point 0 seen by one camera only: its depth is free, the undamped system singular; LM's damping
    # holds it.
    scene = make_scene(num_cameras=4, num_points=50, noise_px=0.5, seed=0)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(0))
    camera_index, point_index, uv = observations(scene)
    seen = ~((point_index == 0) & (camera_index != 1))
    args = (scene.K, poses, points, camera_index[seen], point_index[seen], uv[seen])
    marquardt = bundle_adjust(*args, BundleAdjustmentConfig())
    newton = bundle_adjust(*args, BundleAdjustmentConfig(optimizer="gauss_newton"))
    assert newton.final_cost == pytest.approx(marquardt.final_cost, rel=1e-12)
    np.testing.assert_allclose(newton.points, marquardt.points, atol=1e-12)


def test_iteration_hook_sees_every_iteration_with_a_falling_error():
    scene = make_scene(num_cameras=4, num_points=150, noise_px=0.5, seed=3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    calls = []
    result = run(scene, poses, points, on_iteration=lambda iteration, error: calls.append((iteration, error)))
    assert [iteration for iteration, _ in calls] == list(range(1, result.iterations + 1))
    errors = [error for _, error in calls]
    assert errors == sorted(errors, reverse=True)
    # GTSAM's graph error is the robust cost plus the gauge priors, which stay almost satisfied.
    assert errors[-1] == pytest.approx(result.final_cost, rel=1e-6)


def test_gauge_first_camera_stays_put_and_scale_reference_distance_is_kept():
    scene = make_scene(num_cameras=5, num_points=300, noise_px=1.0, seed=5)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(3), keep=())
    result = run(scene, poses, points, fixed_cameras=(2,), scale_reference=4)
    np.testing.assert_allclose(result.poses[2].R, poses[2].R, atol=1e-9)
    np.testing.assert_allclose(result.poses[2].t, poses[2].t, atol=1e-8)
    distance = np.linalg.norm(poses[4].center - poses[2].center)
    assert np.linalg.norm(result.poses[4].center - result.poses[2].center) == pytest.approx(
        distance, rel=1e-6
    )
    assert not np.allclose(result.poses[4].center, poses[4].center, atol=1e-3)  # it did move otherwise


def test_huber_loss_downweights_outliers():
    scene = make_scene(num_cameras=6, num_points=300, noise_px=0.5, outlier_fraction=0.2, seed=6)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(4))
    robust = run(scene, poses, points, BundleAdjustmentConfig(huber_threshold_px=2.0))
    least_squares = run(scene, poses, points, BundleAdjustmentConfig(huber_threshold_px=1e4))

    robust_errors = aligned_pose_errors(robust.poses, scene.poses)
    plain_errors = aligned_pose_errors(least_squares.poses, scene.poses)
    assert robust_errors.rotation_deg.max() < 0.5
    assert robust_errors.center.max() < 5e-3 * scene.scene_size
    assert robust_errors.center.max() < 0.05 * plain_errors.center.max()
    inliers = scene.inlier_mask
    residuals = reprojection_residuals(scene.K, robust.poses, robust.points, *observations(scene))
    # Most inliers fit to the noise level (median of |N(0, 0.5^2 I_2)| is 0.59 px); a point whose track
    # holds several outliers may still be off, so the median, not the RMS.
    assert np.median(np.linalg.norm(residuals[inliers], axis=1)) < 0.8


def test_local_bundle_adjustment_keeps_fixed_cameras_and_fixes_the_free_ones():
    scene = make_scene(num_cameras=6, num_points=300, noise_px=0.3, seed=7)
    fixed = (0, 1, 2, 3)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(5), keep=fixed)
    config = BundleAdjustmentConfig()
    result = run(scene, poses, points, config, fixed_cameras=fixed, scale_reference=None)
    for camera in fixed:  # held by a near-hard prior: they may move far less than its sigma
        np.testing.assert_allclose(
            result.poses[camera].R, scene.poses[camera].R, atol=0.1 * config.fixed_camera_sigma
        )
        np.testing.assert_allclose(
            result.poses[camera].t, scene.poses[camera].t, atol=0.1 * config.fixed_camera_sigma
        )
    for camera in (4, 5):  # the fixed cameras carry the true gauge, so no alignment is needed
        assert (
            np.linalg.norm(result.poses[camera].center - scene.poses[camera].center) < 1e-3 * scene.scene_size
        )


def test_unobserved_points_and_cameras_are_returned_unchanged():
    scene = make_scene(num_cameras=4, num_points=100, noise_px=0.5, seed=8)
    image_index, track_index, uv = observations(scene)
    keep = (track_index != 7) & (image_index != 3)
    extra_pose = CameraPose.from_center(np.eye(3), np.array([0.0, 0.0, -9.0]))
    poses = [*scene.poses[:3], extra_pose]
    result = bundle_adjust(
        scene.K, poses, scene.points, image_index[keep], track_index[keep], uv[keep], BundleAdjustmentConfig()
    )
    np.testing.assert_array_equal(result.points[7], scene.points[7])
    np.testing.assert_array_equal(result.poses[3].t, extra_pose.t)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda a: {**a, "uv": a["uv"][:-1]}, "same number of observations"),
        (lambda a: {**a, "camera_index": a["camera_index"] + 10}, "camera_index"),
        (lambda a: {**a, "point_index": -a["point_index"] - 1}, "point_index"),
        (lambda a: {**a, "points": a["points"][:, :2]}, "points must be"),
        (lambda a: {**a, "fixed_cameras": ()}, "fixed_cameras"),
        (lambda a: {**a, "scale_reference": 0}, "scale_reference"),
        (lambda a: {**a, "camera": [a["camera"]] * 2}, "2 cameras for 3 poses"),
        (lambda a: {**a, "camera": np.full((3, 3), np.nan)}, "intrinsics must be finite"),
        (lambda a: {**a, "relative_sigma": np.ones(len(a["uv"]) - 1)}, "relative_sigma"),
        (lambda a: {**a, "relative_sigma": np.zeros(len(a["uv"]))}, "relative_sigma"),
    ],
)
def test_bad_input_raises_input_error_naming_the_argument(change, message):
    scene = make_scene(num_cameras=3, num_points=20, seed=9)
    image_index, track_index, uv = observations(scene)
    arguments = {
        "camera": scene.K,
        "poses": scene.poses,
        "points": scene.points,
        "camera_index": image_index,
        "point_index": track_index,
        "uv": uv,
        "config": BundleAdjustmentConfig(),
        "fixed_cameras": (0,),
    }
    with pytest.raises(InputError, match=message):
        bundle_adjust(**change(arguments))


def test_relative_sigmas_are_rounded_to_quarter_octaves():
    levels = noise_levels(np.array([1.0, 1.1, 2.0, 3.0, 1.0]), 5)
    np.testing.assert_allclose(levels.sigmas[levels.level], [1.0, 2**0.25, 2.0, 2**1.5, 1.0])
    assert len(levels.sigmas) == 4                       # one noise model per level
    unweighted = noise_levels(None, 3)
    np.testing.assert_array_equal(unweighted.sigmas[unweighted.level], [1.0, 1.0, 1.0])


def scene_with_coarse_observations(seed=11, noise_px=0.3, coarse_sigma=8.0):
    """A scene with noise_px of pixel noise in which every third observation has coarse_sigma times as much
    (a keypoint found at a coarse scale), and the relative std-dev of each."""
    scene = make_scene(num_cameras=6, num_points=300, noise_px=noise_px, seed=seed)
    image_index, track_index, uv = observations(scene)
    coarse = np.arange(len(uv)) % 3 == 0
    rng = np.random.default_rng(seed)
    noisier = uv + coarse[:, None] * rng.normal(0.0, noise_px * np.sqrt(coarse_sigma**2 - 1), uv.shape)
    return scene, image_index, track_index, noisier, np.where(coarse, coarse_sigma, 1.0)


@pytest.mark.parametrize("refine", [IntrinsicsRefinement(), IntrinsicsRefinement(focal=True)])
def test_observations_with_a_larger_relative_sigma_pull_less(refine):
    scene, image_index, track_index, uv, relative_sigma = scene_with_coarse_observations()
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(3))
    arguments = (scene.K, poses, points, image_index, track_index, uv, BundleAdjustmentConfig())
    alike = bundle_adjust(*arguments, refine=refine)
    weighed = bundle_adjust(*arguments, refine=refine, relative_sigma=relative_sigma)

    error_alike = aligned_pose_errors(alike.poses, scene.poses).rotation_deg.mean()
    error_weighed = aligned_pose_errors(weighed.poses, scene.poses).rotation_deg.mean()
    assert error_weighed < 0.7 * error_alike
    # The cost is of the whitened residuals, the one the optimizer lowered.
    residuals = weighed.final_residuals / relative_sigma[:, None]
    assert weighed.final_cost == pytest.approx(huber_cost(residuals, 2.0))
    assert weighed.final_cost < weighed.initial_cost


# --- intrinsics -----------------------------------------------------------------------------------

TRUE_RADIAL = Camera("radial", fx=600.0, fy=600.0, cx=400.0, cy=300.0, k1=-0.15, k2=0.02)


def prior_camera(model, width=800, height=600):
    """COLMAP's prior: focal 1.2 max(w, h), no distortion, principal point at the centre."""
    focal = 1.2 * max(width, height)
    return Camera(model, fx=focal, fy=focal, cx=400.0, cy=300.0)


@pytest.mark.parametrize("model", ["simple-radial", "radial", "opencv"])
def test_gtsam_calibrations_project_like_the_projection_module(model):
    camera = TRUE_RADIAL.as_model(model)
    scene = make_scene(num_cameras=2, num_points=30, seed=1, camera=camera)
    pose = scene.poses[1]
    gtsam_camera = (gtsam.PinholeCameraCal3Bundler if model != "opencv" else gtsam.PinholeCameraCal3DS2)(
        camera_pose_to_gtsam(pose), camera_to_gtsam(camera))
    ours = project(camera, pose, scene.points)
    np.testing.assert_allclose([gtsam_camera.project(p) for p in scene.points], ours, atol=1e-8)


@pytest.mark.parametrize(("model", "truth"), [("radial", TRUE_RADIAL),
                                              ("simple-radial", TRUE_RADIAL.as_model("simple-radial"))])
def test_shared_focal_and_distortion_are_recovered_from_the_prior(model, truth):
    scene = make_scene(num_cameras=8, num_points=400, noise_px=0.5, seed=3, camera=truth)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(0))
    result = bundle_adjust(prior_camera(model), poses, points, *observations(scene), BundleAdjustmentConfig(),
                           refine=IntrinsicsRefinement(focal=True, distortion=True))
    camera = result.cameras[0]
    assert all(c is camera for c in result.cameras)                 # one shared calibration
    assert camera.fx == pytest.approx(truth.fx, rel=0.005)
    assert camera.k1 == pytest.approx(truth.k1, rel=0.10)
    assert (camera.cx, camera.cy) == (400.0, 300.0)                 # the principal point is held
    assert result.final_rms_px < 0.75                               # ~ the noise: sqrt(2) * 0.5 px
    errors = aligned_pose_errors(result.poses, scene.poses)
    assert errors.rotation_deg.max() < 0.1


def test_per_image_calibrations_are_refined_separately():
    scene = make_scene(num_cameras=8, num_points=400, noise_px=0.3, seed=4, camera=TRUE_RADIAL)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(1))
    start = [prior_camera("radial")] * 8
    result = bundle_adjust(start, poses, points, *observations(scene), BundleAdjustmentConfig(),
                           refine=IntrinsicsRefinement(focal=True, distortion=True, per_image=True))
    focals = np.array([c.fx for c in result.cameras])
    assert len(set(focals.tolist())) == 8                            # eight calibration variables
    np.testing.assert_allclose(focals, TRUE_RADIAL.fx, rtol=0.02)


def test_fixed_intrinsics_stay_as_given_and_distorted_pixels_are_undistorted_first():
    scene = make_scene(num_cameras=5, num_points=200, noise_px=0.0, seed=5, camera=TRUE_RADIAL)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(2))
    result = bundle_adjust(TRUE_RADIAL, poses, points, *observations(scene), BundleAdjustmentConfig())
    assert result.cameras == [TRUE_RADIAL] * 5
    assert result.final_rms_px < 1e-4
    assert aligned_pose_errors(result.poses, scene.poses).rotation_deg.max() < 1e-4


def test_marked_ids_are_the_sorted_unique_union_np_unique_gives():
    ids = np.array([7, 2, 2, 9]), [0, 7]
    marked = _marked(12, *ids)
    assert marked.shape == (12,)
    np.testing.assert_array_equal(np.flatnonzero(marked), np.unique(np.concatenate(ids)))


def test_the_pinhole_calibration_is_the_cameras_K():
    camera = Camera("opencv", fx=810.0, fy=805.0, cx=402.0, cy=297.0, skew=0.5, k1=-0.2)
    np.testing.assert_array_equal(_pinhole_calibration(camera).K(), camera.K)


def test_one_shared_camera_object_adjusts_bitwise_as_equal_per_image_copies():
    # A shared object is used as is (`observation_cameras`), copies per observation: the same arithmetic.
    scene = make_scene(num_cameras=5, num_points=150, noise_px=0.5, seed=6, camera=TRUE_RADIAL)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(3), keep=(0, 1, 2))
    results = [
        bundle_adjust(cameras, poses, points, *observations(scene), BundleAdjustmentConfig(),
                      fixed_cameras=(0, 1, 2), scale_reference=None)
        for cameras in ([TRUE_RADIAL] * 5, [replace(TRUE_RADIAL) for _ in range(5)])
    ]
    shared, copies = results
    np.testing.assert_array_equal(shared.points, copies.points)
    for a, b in zip(shared.poses, copies.poses, strict=True):
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(shared.initial_residuals, copies.initial_residuals)
    np.testing.assert_array_equal(shared.final_residuals, copies.final_residuals)


def test_the_principal_point_is_refined_on_request_for_the_opencv_model():
    truth = Camera("opencv", fx=600.0, fy=605.0, cx=390.0, cy=310.0, k1=-0.1, k2=0.01, p1=1e-3, p2=-1e-3)
    scene = make_scene(num_cameras=10, num_points=500, noise_px=0.3, seed=6, camera=truth)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(3))
    refine = IntrinsicsRefinement(focal=True, distortion=True, principal_point=True)
    result = bundle_adjust(prior_camera("opencv"), poses, points, *observations(scene),
                           BundleAdjustmentConfig(), refine=refine)
    camera = result.cameras[0]
    assert np.hypot(camera.cx - truth.cx, camera.cy - truth.cy) < 3.0     # started 10.8 px away
    assert camera.fx == pytest.approx(truth.fx, rel=0.01) and camera.fy == pytest.approx(truth.fy, rel=0.01)


@pytest.mark.parametrize("model", ["simple-radial", "radial"])
def test_a_one_focal_model_refines_its_principal_point_with_fx_equal_to_fy(model):
    truth = TRUE_RADIAL.as_model(model)
    truth = Camera(model, fx=truth.fx, fy=truth.fy, cx=412.0, cy=291.0, k1=truth.k1, k2=truth.k2)
    scene = make_scene(num_cameras=8, num_points=400, noise_px=0.3, seed=6, camera=truth)
    poses, points = perturbed(scene.poses, scene.points, np.random.default_rng(3))
    result = bundle_adjust(prior_camera(model), poses, points, *observations(scene), BundleAdjustmentConfig(),
                           refine=IntrinsicsRefinement(focal=True, distortion=True, principal_point=True))
    camera = result.cameras[0]
    assert camera.model == model and camera.fx == camera.fy            # one focal length, as exported
    assert camera.fx == pytest.approx(truth.fx, rel=0.005)
    assert np.hypot(camera.cx - truth.cx, camera.cy - truth.cy) < 1.5  # started 15 px away
    assert camera.k1 == pytest.approx(truth.k1, rel=0.10)
    assert aligned_pose_errors(result.poses, scene.poses).rotation_deg.max() < 0.1


def test_point_covariances_are_gtsams_marginals_and_the_noise_is_measured_from_the_residuals():
    scene = make_scene(num_cameras=4, num_points=40, noise_px=0.5, seed=3)
    config = BundleAdjustmentConfig()
    result = run(scene, scene.poses, scene.points, config, point_covariances=True)
    assert result.measured_pixel_sigma == pytest.approx(0.5, rel=0.1)
    # The reference: gtsam.Marginals on the same least-squares problem (the residuals are far below the
    # Huber threshold, so the robust weights are 1), the first camera held by a prior, the scale by a range.
    pixel_noise = gtsam.noiseModel.Isotropic.Sigma(2, config.measurement_sigma_px)
    calibration = _pinhole_calibration(Camera.from_K(scene.K))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    point_key = len(scene.poses)
    for camera, point, uv in zip(*observations(scene), strict=True):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(uv, pixel_noise, int(camera), point_key + int(point),
                                                       calibration))
    for camera, pose in enumerate(result.poses):
        values.insert(camera, camera_pose_to_gtsam(pose))
    for point, xyz in enumerate(result.points):
        values.insert(point_key + point, xyz)
    graph.add(gtsam.PriorFactorPose3(0, values.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-7)))
    distance = float(np.linalg.norm(result.poses[0].center - result.poses[1].center))
    graph.add(gtsam.RangeFactorPose3(0, 1, distance, gtsam.noiseModel.Isotropic.Sigma(
        1, config.scale_sigma_relative * distance)))
    marginals = gtsam.Marginals(graph, values)
    for point in (0, 17, 39):
        np.testing.assert_allclose(result.point_covariances[point],
                                   marginals.marginalCovariance(point_key + point), rtol=1e-3, atol=1e-12)
    assert result.point_covariances.shape == (40, 3, 3)


def test_a_definite_information_gives_its_inverse_and_an_indeterminate_one_its_pseudo_inverse():
    rows = np.random.default_rng(0).normal(size=(6, 8))
    definite = rows @ rows.T
    np.testing.assert_allclose(_covariance_of(definite) @ definite, np.eye(6), atol=1e-9)
    indeterminate = rows[:4].T @ rows[:4]          # 8 x 8 of rank 4
    np.testing.assert_allclose(_covariance_of(indeterminate), np.linalg.pinv(indeterminate), atol=1e-9)


def test_point_covariances_are_refused_with_refined_intrinsics():
    scene = make_scene(num_cameras=3, num_points=30, seed=1)
    with pytest.raises(InputError, match="intrinsics held"):
        run(scene, scene.poses, scene.points, point_covariances=True, refine=IntrinsicsRefinement(focal=True))
