"""Each registration is held against evidence it was not fitted to: its support and spread, and the
relative rotations that two-view geometry verified for its pairs; a finished model against the points its
cameras at one viewpoint should share."""

from dataclasses import replace

import numpy as np
import pytest

from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement
from estimation.config import ReconstructionConfig
from estimation.geometry.alignment import aligned_pose_errors, relative_pose
from estimation.geometry.linalg import skew
from estimation.geometry.projection import Camera
from estimation.mapper.incremental import reconstruct_models
from estimation.mapper.verification import (
    LOOSE_ROTATION,
    InlierSupport,
    VerifiedPair,
    agreement_problem,
    epipolar_share,
    essential_rotation_deviations_deg,
    inlier_spread,
    pair_fundamental,
    pose_fundamental,
    pose_rotation_std_deg,
    rotation_agreement,
    rotation_std_problem,
    shared_views,
    support_problem,
    under_intrinsics,
    voting_pairs,
)
from estimation.synthetic import make_symmetric_ring, rotation_about_axis
from estimation.two_view.essential import essential_rotations
from estimation.two_view.geometry import TwoViewGeometry, TwoViewGeometryType, verify_epipolar
from estimation.types import CameraPose


def essential_of(pose: CameraPose) -> np.ndarray:
    """E = [t]x R of a relative pose (x_2 = R x_1 + t)."""
    return skew(pose.t) @ pose.R


def test_inliers_over_the_whole_image_have_full_spread_and_a_corner_has_little():
    grid = np.stack(np.meshgrid(np.linspace(0, 399, 40), np.linspace(0, 299, 30)), axis=-1).reshape(-1, 2)
    assert inlier_spread(grid, 400, 300) == 1.0
    corner = grid[(grid[:, 0] < 100) & (grid[:, 1] < 75)]
    assert inlier_spread(corner, 400, 300) == pytest.approx(4 / 64)
    assert inlier_spread(corner[:0], 400, 300) == 0.0


def test_support_is_refused_below_each_of_its_three_minimums_and_names_the_numbers():
    assert support_problem(InlierSupport(40, 100, 0.8), 30, 0.25, 0.25) is None
    assert "12 inliers among 100" in support_problem(InlierSupport(12, 100, 0.8), 30, 0.25, 0.25)
    assert "need 30 and 25%" in support_problem(InlierSupport(40, 200, 0.8), 30, 0.25, 0.25)
    assert "lie in 10% of the image's 8x8 cells" in support_problem(InlierSupport(40, 100, 0.1), 30, 0.25,
                                                                     0.25)


def pixels(K: np.ndarray, pose: CameraPose, points: np.ndarray) -> np.ndarray:
    camera = points @ pose.R.T + pose.t
    return (camera @ K.T)[:, :2] / camera[:, 2:]


@pytest.fixture
def camera_and_points():
    """A 400x300 camera 5 units in front of 40 points spread over its view and 1 unit deep, and 12 points
    on a shallow patch covering a tenth of its width."""
    K = np.array([[500.0, 0.0, 200.0], [0.0, 500.0, 150.0], [0.0, 0.0, 1.0]])
    pose = CameraPose(rotation_about_axis(np.array([0.2, 1.0, 0.1]), np.radians(20)),
                      np.array([0.1, -0.2, 5.0]))
    rng = np.random.default_rng(0)
    camera_points = np.column_stack([rng.uniform(-1.5, 1.5, 40), rng.uniform(-1.1, 1.1, 40),
                                     rng.uniform(-0.5, 0.5, 40)]) + [0.0, 0.0, 5.0]
    patch_points = np.column_stack([rng.uniform(0.65, 0.95, 12), rng.uniform(0.35, 0.65, 12),
                                    rng.uniform(-0.05, 0.05, 12)]) + [0.0, 0.0, 5.0]
    def world(camera: np.ndarray) -> np.ndarray:
        return (camera - pose.t) @ pose.R     # X = R^T (x - t)
    return K, pose, world(camera_points), world(patch_points)


def test_the_rotation_std_is_the_covariance_of_a_rotation_perturbation_at_the_pixel_noise(camera_and_points):
    K, pose, points, _ = camera_and_points
    # J by finite differences of the pixels under R <- exp([w]x) R, t <- t + dt
    step, columns = 1e-6, []
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = step
        rotated = rotation_about_axis(delta[:3], step) @ pose.R if k < 3 else pose.R
        moved = CameraPose(rotated, pose.t + delta[3:])
        columns.append(((pixels(K, moved, points) - pixels(K, pose, points)) / step).ravel())
    covariance = 0.5**2 * np.linalg.inv(np.column_stack(columns).T @ np.column_stack(columns))[:3, :3]
    expected = np.degrees(np.sqrt(np.linalg.eigvalsh(covariance).max()))
    assert pose_rotation_std_deg(K, pose, points, 0.5) == pytest.approx(expected, rel=1e-4)
    assert pose_rotation_std_deg(K, pose, points, 1.0) == pytest.approx(
        2 * pose_rotation_std_deg(K, pose, points, 0.5), rel=1e-9)


def test_a_dozen_points_on_one_patch_pin_the_rotation_far_less_than_points_over_the_view(camera_and_points):
    K, pose, points, patch = camera_and_points
    spread = pose_rotation_std_deg(K, pose, points[:12], 1.0)
    clustered = pose_rotation_std_deg(K, pose, patch, 1.0)
    assert clustered > 4 * spread
    assert pose_rotation_std_deg(K, pose, patch[:2], 1.0) == np.inf     # two points cannot fix six unknowns


def test_a_loosely_pinned_rotation_is_refused_naming_its_std_and_the_limit():
    assert rotation_std_problem(2.9, 3.0, 13) is None
    problem = rotation_std_problem(4.4, 3.0, 13)
    assert "13 inliers determine its rotation only to 4.4 deg" in problem and "need 3 deg" in problem
    assert problem.endswith(LOOSE_ROTATION)


def test_a_relative_rotation_agrees_with_its_own_essential_matrix_and_a_half_turn_does_not():
    relative = CameraPose(rotation_about_axis(np.array([0.1, 1.0, 0.0]), np.radians(7)),
                          np.array([1.0, 0.0, 0.1]))
    E = essential_of(relative)
    assert essential_rotation_deviations_deg(essential_rotations(E), relative.R) < 1e-6
    # E is up to scale and sign
    assert essential_rotation_deviations_deg(essential_rotations(-3.0 * E), relative.R) < 1e-6
    flipped = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.pi) @ relative.R
    assert essential_rotation_deviations_deg(essential_rotations(E), flipped) > 170
    # stacked pairs: one deviation each
    stacked = essential_rotation_deviations_deg(np.stack([essential_rotations(E)] * 2),
                                                np.stack([relative.R, flipped]))
    assert stacked.shape == (2,) and stacked[0] < 1e-6 and stacked[1] > 170


def test_voting_pairs_orient_each_pair_from_the_voting_image_and_skip_weak_pairs():
    poses = [CameraPose.from_center(rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(a)),
                                    np.array([np.sin(np.radians(a)), 0.0, -np.cos(np.radians(a))]) * 5)
             for a in (0, 10, 20)]
    E_01 = essential_of(relative_pose(poses[0], poses[1]))     # x_1^T E x_0 = 0
    strong = TwoViewGeometry(TwoViewGeometryType.CALIBRATED, np.ones(50, bool), None, E_01, None, 50, 50, 0)
    weak = TwoViewGeometry(TwoViewGeometryType.CALIBRATED, np.ones(10, bool), None, E_01, None, 10, 10, 0)
    votes = voting_pairs({(0, 1): strong, (1, 2): weak}, 3, min_inliers=30)
    assert [pair.other for pair in votes[0]] == [1] and [pair.other for pair in votes[1]] == [0]
    assert votes[2] == []
    R_of = {m: pose.R for m, pose in enumerate(poses)}
    for image in (0, 1):
        agreement = rotation_agreement(poses[image].R, votes[image], R_of, max_deviation_deg=5)
        assert agreement.share == 1.0 and agreement.voting_inliers == 50


def test_one_disagreeing_strong_pair_vetoes_a_rotation_at_full_agreement_and_names_the_pair():
    turn = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.pi)
    R_of = {1: np.eye(3), 2: np.eye(3)}
    baseline = skew(np.array([1.0, 0.0, 0.0]))
    pairs = [VerifiedPair(1, essential_rotations(baseline), 200),
             VerifiedPair(2, essential_rotations(baseline @ turn), 100)]
    agreement = rotation_agreement(np.eye(3), pairs, R_of, max_deviation_deg=30)
    assert agreement.agreeing_inliers == 200 and agreement.share == pytest.approx(2 / 3)
    assert agreement_problem(agreement, 0.5, ["a", "b", "c"]) is None
    problem = agreement_problem(agreement, 1.0, ["a", "b", "c"])
    assert "180 deg off the pair with c" in problem and "near-mirror" in problem
    assert rotation_agreement(np.eye(3), [], R_of, 30).share == 1.0     # no vote contradicts


def pixel_K(focal: float) -> np.ndarray:
    return np.array([[focal, 0.0, 320.0], [0.0, focal, 240.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def wide_pair():
    """Two views 40 deg apart around a point 5 units ahead of the first, focal length 576 px."""
    return [CameraPose.from_center(rotation_about_axis(np.array([0.1, 1.0, 0.0]), np.radians(a)),
                                   np.array([np.sin(np.radians(a)), 0.1, -np.cos(np.radians(a))]) * 5)
            for a in (0, 40)]


def uncalibrated_votes(F_01: np.ndarray) -> list[list[VerifiedPair]]:
    """The votes of a pair (0, 1) verified with F only, x_1^T F x_0 = 0."""
    geometry = TwoViewGeometry(TwoViewGeometryType.UNCALIBRATED, np.ones(80, bool), F_01, None, None,
                               80, 0, 0)
    return voting_pairs({(0, 1): geometry}, 2, min_inliers=30)


def test_a_pair_verified_without_calibration_votes_with_F_under_the_refined_focal_not_the_prior(wide_pair):
    """F's E = K^T F K turns with K: under a focal prior 1.33x the truth (1.2 x the image side where the
    truth is 0.9 x, as on Strecha's photos) the 40 deg pair's rotation comes out ~12 deg off; under the
    refined focal it is the truth, and a far-side placement is still refused."""
    true_K, prior_K, min_ratio = pixel_K(576.0), pixel_K(768.0), 0.85
    K_inverse = np.linalg.inv(true_K)
    votes = uncalibrated_votes(K_inverse.T @ essential_of(relative_pose(*wide_pair)) @ K_inverse)
    assert votes[1][0].rotations is None and votes[0][0].rotations is None    # they follow the intrinsics
    R_of = {m: pose.R for m, pose in enumerate(wide_pair)}
    turn = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.pi)
    limit = 5.0
    for image, other in ((1, 0), (0, 1)):
        under_prior = [under_intrinsics(votes[image][0], prior_K, prior_K, min_ratio)]
        off = rotation_agreement(wide_pair[image].R, under_prior, R_of, limit).deviations_deg[other]
        assert off > 2 * limit
        refined = [under_intrinsics(votes[image][0], true_K, true_K, min_ratio)]
        agreement = rotation_agreement(wide_pair[image].R, refined, R_of, limit)
        assert agreement.share == 1.0 and agreement.deviations_deg[other] < 1e-6
        flipped = rotation_agreement(turn @ wide_pair[image].R, refined, R_of, limit)
        assert flipped.share == 0.0
        assert "near-mirror" in agreement_problem(flipped, 1.0, ["a", "b"])


def test_an_F_that_fits_a_planar_pair_but_not_the_camera_does_not_vote(wide_pair):
    """Matches on one plane fit F = [e]x H for any epipole e: one F of that family explains every match,
    yet under the true K its E has unequal singular values (and a rotation ~40 deg off): no vote."""
    K = pixel_K(576.0)
    relative = relative_pose(*wide_pair)
    plane_normal, plane_distance = np.array([0.0, 0.0, 1.0]), 5.0    # z = 5 in the first camera
    H = K @ (relative.R + np.outer(relative.t, plane_normal) / plane_distance) @ np.linalg.inv(K)
    F = skew(np.array([300.0, 200.0, 1.0])) @ H
    plane = np.column_stack([np.random.default_rng(0).uniform(-1, 1, (20, 2)), np.full(20, plane_distance)])
    x_0, x_1 = plane @ K.T, (plane @ relative.R.T + relative.t) @ K.T
    assert np.abs(np.einsum("ni,ij,nj->n", x_1 / x_1[:, 2:], F, x_0 / x_0[:, 2:])).max() < 1e-9
    votes = uncalibrated_votes(F)
    assert under_intrinsics(votes[1][0], K, K, min_singular_ratio=0.85) is None
    assert under_intrinsics(votes[1][0], K, K, min_singular_ratio=0.0) is not None


def test_a_pair_with_a_verified_essential_matrix_keeps_its_rotations_whatever_the_intrinsics():
    pair = VerifiedPair(1, essential_rotations(skew(np.array([1.0, 0.0, 0.0]))), 50)
    assert under_intrinsics(pair, np.eye(3), 2 * np.eye(3), min_singular_ratio=0.85) is pair


def verified_pairs(scene, K: np.ndarray | None) -> dict[tuple[int, int], TwoViewGeometry]:
    """The pairs sharing 40+ tracks verified as the front end does (with K: E; without: F only)."""
    config = ReconstructionConfig()
    geometries = {}
    for i in range(len(scene.poses)):
        for j in range(i + 1, len(scene.poses)):
            _, uv_i, uv_j = scene.tracks.pair_correspondences(i, j)
            if len(uv_i) >= 40:
                geometries[(i, j)] = verify_epipolar(uv_i, uv_j, K, K, config.two_view, config.ransac)
    return geometries


@pytest.fixture(scope="module")
def symmetric_ring():
    """A 16-view ring around a half-turn symmetric object; image 5 matched 60 % of its features to the
    far side; its pairs verified with the true K (`verified_pairs`)."""
    ring = make_symmetric_ring(num_cameras=16, num_points=2000, confused=(5,), confusion=0.6, seed=0)
    return ring, verified_pairs(ring.scene, ring.scene.K)


def rotation_errors(model, scene) -> dict[int, float]:
    registered = sorted(model.poses)
    errors = aligned_pose_errors([model.poses[m] for m in registered], [scene.poses[m] for m in registered])
    return dict(zip(registered, errors.rotation_deg, strict=True))


def test_without_the_pairs_geometry_the_confused_image_is_placed_on_the_far_side(symmetric_ring):
    ring, _ = symmetric_ring
    model = reconstruct_models(ring.scene.tracks, ring.scene.K, ReconstructionConfig())[0]
    assert rotation_errors(model, ring.scene)[5] > 170     # its support alone cannot tell


def test_the_verified_pairs_refuse_the_mirrored_placement_and_every_registered_image_is_right(symmetric_ring):
    ring, geometries = symmetric_ring
    model = reconstruct_models(ring.scene.tracks, ring.scene.K, ReconstructionConfig(),
                               pair_geometries=geometries)[0]
    errors = rotation_errors(model, ring.scene)
    assert max(errors.values()) < 1.0
    assert len(errors) >= 15
    assert 5 not in model.poses
    assert "near-mirror" in model.unregistered[5]
    assert any(check.image == 5 and check.event == "refused" for check in model.checks)
    assert any("near-mirror ambiguity" in warning and "6.png" in warning for warning in model.warnings)


def test_without_calibration_the_pairs_F_still_refuse_the_mirrored_placement(symmetric_ring):
    """The pairs verified with F only and a focal prior 1.3x the truth, refined by the BAs: the votes follow
    the refined focal, and the far-side placement of image 5 is refused as with calibration."""
    ring, _ = symmetric_ring
    scene = ring.scene
    geometries = verified_pairs(scene, None)
    assert all(geometry.E is None for geometry in geometries.values())
    prior = scene.K @ np.diag([1.3, 1.3, 1.0])
    model = reconstruct_models(scene.tracks, prior, ReconstructionConfig(),
                               refine=IntrinsicsRefinement(focal=True),
                               pair_geometries=geometries)[0]
    errors = rotation_errors(model, scene)
    assert max(errors.values()) < 1.0 and len(errors) >= 15
    assert 5 not in model.poses and "near-mirror" in model.unregistered[5]
    assert model.cameras[0].fx == pytest.approx(scene.K[0, 0], rel=0.01)


def test_the_poses_epipolar_geometry_explains_the_true_correspondences_and_a_mirrored_pose_does_not(
        symmetric_ring):
    ring, _ = symmetric_ring
    scene = ring.scene
    _, uv_9, uv_8 = scene.tracks.pair_correspondences(9, 8)
    true_F = pose_fundamental(scene.K, scene.poses[9], scene.poses[8])
    assert epipolar_share(true_F, uv_9, uv_8, threshold_px=4.0) > 0.95
    # The same camera turned half around the ring's axis: a far-side placement.
    half_turn = rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.pi)
    mirrored = CameraPose(R=scene.poses[9].R @ half_turn, t=scene.poses[9].t)
    assert epipolar_share(pose_fundamental(scene.K, mirrored, scene.poses[8]), uv_9, uv_8, 4.0) < 0.2
    # A pair's own E gives the same F as the poses it was verified from.
    relative = relative_pose(scene.poses[8], scene.poses[9])
    pair = VerifiedPair(8, None, len(uv_9), E=skew(relative.t) @ relative.R)
    F = pair_fundamental(pair, scene.K)
    np.testing.assert_allclose(F / np.linalg.norm(F), true_F / np.linalg.norm(true_F), atol=1e-9)


def test_a_pair_whose_own_E_is_off_does_not_veto_a_pose_that_explains_its_correspondences(symmetric_ring):
    """Pair (9, 10)'s E replaced by one 70 deg off: its rotation alone would veto the true poses, but they
    explain the pair's correspondences far better than that E does, so both register, and the mirrored
    placement of image 5 is still refused."""
    ring, geometries = symmetric_ring
    scene = ring.scene
    relative = relative_pose(scene.poses[9], scene.poses[10])
    turned = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(70)) @ relative.R
    wrong_E = skew(relative.t) @ turned
    max_deviation = ReconstructionConfig().mapper.verify_max_rotation_deviation_deg
    alone = rotation_agreement(scene.poses[10].R, [VerifiedPair(9, essential_rotations(wrong_E), 345)],
                               {9: scene.poses[9].R}, max_deviation)
    assert alone.share == 0.0
    wrong = {**geometries, (9, 10): replace(geometries[(9, 10)], E=wrong_E)}
    model = reconstruct_models(scene.tracks, scene.K, ReconstructionConfig(), pair_geometries=wrong)[0]
    errors = rotation_errors(model, scene)
    assert 9 in errors and 10 in errors and max(errors.values()) < 1.0
    assert 5 not in model.poses and "near-mirror" in model.unregistered[5]


VIEW_K = np.array([[100.0, 0.0, 49.5], [0.0, 100.0, 49.5], [0.0, 0.0, 1.0]])
VIEW_SIZE = (100, 100)


def turned(degrees: float) -> CameraPose:
    """A camera at the origin turned about its y axis."""
    return CameraPose(R=rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(degrees)), t=np.zeros(3))


def views_of(poses: dict[int, CameraPose], points: np.ndarray, observed: dict[int, np.ndarray]):
    """`shared_views` within 5 deg, every camera the pinhole VIEW_K."""
    obs_image = np.concatenate([np.full(len(index), m) for m, index in observed.items()])
    obs_point = np.concatenate(list(observed.values()))
    return shared_views(poses, [Camera.from_K(VIEW_K)] * (max(poses) + 1), VIEW_SIZE, points, obs_image,
                        obs_point, max_angle_deg=5.0)


@pytest.fixture
def grid_points():
    """100 points on a 10 x 10 grid 5 in front of the origin, inside a 100 px image at f = 100."""
    x, y = np.meshgrid(np.linspace(-2.0, 2.0, 10), np.linspace(-2.0, 2.0, 10))
    return np.column_stack([x.ravel(), y.ravel(), np.full(100, 5.0)])


def test_cameras_at_one_viewpoint_that_observe_the_same_points_share_all_of_them(grid_points):
    views = views_of({0: turned(0.0), 1: turned(1.0)}, grid_points, {0: np.arange(100), 1: np.arange(100)})
    assert [(view.image_a, view.image_b) for view in views] == [(0, 1)]
    assert views[0].shared == pytest.approx(1.0)
    assert views[0].angle_deg == pytest.approx(1.0)


def test_a_camera_at_the_viewpoint_that_observes_half_of_the_points_shares_half(grid_points):
    # 1 -> 0: all of 1's points are 0's (1.0); 0 -> 1: half of 0's points inside 1 are 1's (0.5)
    views = views_of({0: turned(0.0), 1: turned(1.0)}, grid_points, {0: np.arange(100), 1: np.arange(50)})
    assert views[0].shared == pytest.approx(0.5)


def test_points_outside_the_other_image_do_not_count_against_the_pair(grid_points):
    aside = grid_points + [40.0, 0.0, 0.0]       # far right of both images
    points = np.vstack([grid_points, aside])
    views = views_of({0: turned(0.0), 1: turned(1.0)}, points, {0: np.arange(200), 1: np.arange(100)})
    assert views[0].shared == pytest.approx(1.0)


def test_cameras_farther_apart_than_the_angle_are_not_compared(grid_points):
    views = views_of({0: turned(0.0), 1: turned(8.0), 2: CameraPose(R=np.eye(3), t=np.array([-1.0, 0, 0]))},
                     grid_points, {m: np.arange(100) for m in range(3)})
    # 8 deg of rotation, and a baseline of 1 seen from points 5 away (11 deg)
    assert views == []
