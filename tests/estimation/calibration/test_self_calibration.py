"""Self-calibration of the focal length from the pairs' fundamental matrices: found from a prior 40 % off on
a façade-like capture (optical axes in many directions), refused on a ring whose axes all pass through the
object's centre (F does not determine the focal length there), and used by the pipeline only in place of
the prior."""

from __future__ import annotations

import numpy as np
import pytest

from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement
from estimation.calibration.self_calibration import essential_defect, focal_from_fundamentals
from estimation.config import ReconstructionConfig
from estimation.geometry.linalg import skew
from estimation.geometry.projection import Camera
from estimation.pipeline import FOCAL_FROM_PAIRS, InitialIntrinsics, self_calibrated
from estimation.synthetic import look_at, project, rotation_about_axis
from estimation.two_view.fundamental import eight_point
from estimation.two_view.geometry import TwoViewGeometry, TwoViewGeometryType
from estimation.types import CameraPose

WIDTH, HEIGHT, FOCAL = 1200, 800, 1000.0
TRUE_K = np.array([[FOCAL, 0, (WIDTH - 1) / 2], [0, FOCAL, (HEIGHT - 1) / 2], [0, 0, 1]])
PRIOR = 1.4 * FOCAL
CONFIG = ReconstructionConfig().camera


def facade_poses(rng: np.random.Generator, num_cameras: int = 8) -> list[CameraPose]:
    """Cameras along a street in front of a wall (z = 0..3), each turned its own way by up to 15 deg."""
    poses = []
    for x in np.linspace(-3, 3, num_cameras):
        center = np.array([x, rng.uniform(-0.3, 0.3), -6 + rng.uniform(-0.5, 0.5)])
        R = look_at(center, center + [0, 0, 1], np.array([0.0, -1.0, 0.0]))
        for axis in ([0, 1, 0], [1, 0, 0], [0, 0, 1]):
            R = rotation_about_axis(np.array(axis, float), np.deg2rad(rng.uniform(-15, 15))) @ R
        poses.append(CameraPose.from_center(R, center))
    return poses


def ring_poses(num_cameras: int = 8) -> list[CameraPose]:
    """Cameras on a circle around the origin, every one looking at it."""
    poses = []
    for azimuth in np.deg2rad(np.linspace(0, 90, num_cameras)):
        center = 6 * np.array([np.sin(azimuth), 0.0, -np.cos(azimuth)])
        poses.append(CameraPose.from_center(look_at(center, np.zeros(3), np.array([0.0, -1.0, 0.0])), center))
    return poses


def fundamentals(poses: list[CameraPose], points: np.ndarray, noise_px: float, rng: np.random.Generator
                 ) -> list[np.ndarray]:
    """F of every pair (x_j^T F x_i = 0) by the eight-point method from noisy projections of the points
    in front of both cameras and inside both images."""
    found = []
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            uv_i, uv_j = project(TRUE_K, poses[i], points), project(TRUE_K, poses[j], points)
            inside = np.ones(len(points), bool)
            for pose, uv in ((poses[i], uv_i), (poses[j], uv_j)):
                inside &= (points @ pose.R.T + pose.t)[:, 2] > 0
                inside &= (uv >= 0).all(axis=1) & (uv[:, 0] < WIDTH) & (uv[:, 1] < HEIGHT)
            if inside.sum() < 50:
                continue
            noisy = [uv[inside] + rng.normal(0, noise_px, (inside.sum(), 2)) for uv in (uv_i, uv_j)]
            found.append(eight_point(*noisy))
    return found


def wall_points(rng: np.random.Generator, count: int = 2000) -> np.ndarray:
    return rng.uniform([-6, -3, 0], [6, 3, 3], (count, 3))


def test_an_essential_matrix_has_no_defect_under_the_true_intrinsics_and_one_under_a_wrong_focal():
    rng = np.random.default_rng(0)
    first, second = facade_poses(rng, 2)
    R = second.R @ first.R.T
    t = second.t - R @ first.t
    F = np.linalg.inv(TRUE_K).T @ skew(t) @ R @ np.linalg.inv(TRUE_K)
    wrong = TRUE_K.copy()
    wrong[0, 0] = wrong[1, 1] = 1.3 * FOCAL
    defect = essential_defect(F[None], np.stack([TRUE_K, wrong]))
    assert defect.shape == (2, 1)
    assert defect[0, 0] < 1e-9 < 1e-3 < defect[1, 0]


def test_a_facade_capture_gives_the_focal_length_from_a_prior_40_percent_off():
    rng = np.random.default_rng(1)
    F = fundamentals(facade_poses(rng), wall_points(rng), 0.5, rng)
    found = focal_from_fundamentals(np.array(F), np.full(len(F), 100), ((WIDTH - 1) / 2, (HEIGHT - 1) / 2),
                                    PRIOR, CONFIG.focal_search_factor, CONFIG.focal_min_contrast)
    assert found.reason == "" and found.pairs == len(F)
    assert found.focal_px == pytest.approx(FOCAL, rel=0.03)
    assert found.contrast >= CONFIG.focal_min_contrast


def test_a_ring_looking_at_one_point_leaves_the_focal_length_undetermined_and_is_refused():
    rng = np.random.default_rng(2)
    F = fundamentals(ring_poses(), rng.uniform(-1, 1, (2000, 3)), 0.5, rng)
    found = focal_from_fundamentals(np.array(F), np.full(len(F), 100), ((WIDTH - 1) / 2, (HEIGHT - 1) / 2),
                                    PRIOR, CONFIG.focal_search_factor, CONFIG.focal_min_contrast)
    assert found.focal_px is None and "optical axes through one point" in found.reason


def test_without_pairs_nothing_is_found():
    found = focal_from_fundamentals(np.zeros((0, 3, 3)), np.zeros(0), (0.0, 0.0), PRIOR, 3.0, 1.3)
    assert found.focal_px is None and found.pairs == 0


def geometries(F: list[np.ndarray], inliers: int = 100) -> dict[tuple[int, int], TwoViewGeometry]:
    return {(k, k + 1): TwoViewGeometry(TwoViewGeometryType.UNCALIBRATED, np.ones(inliers, bool), each, None,
                                        None, inliers, 0, 0) for k, each in enumerate(F)}


def prior_intrinsics(source: str = "prior", per_image: bool = False) -> InitialIntrinsics:
    camera = Camera("simple-radial", fx=PRIOR, fy=PRIOR, cx=(WIDTH - 1) / 2, cy=(HEIGHT - 1) / 2)
    refine = IntrinsicsRefinement(focal=True, distortion=True, per_image=per_image)
    return InitialIntrinsics([camera] * 3, source, [source] * 3, refine, ["prior"])


def test_the_pipeline_starts_from_the_pairs_focal_length_only_in_place_of_the_prior_of_a_shared_camera():
    rng = np.random.default_rng(1)
    pairs = geometries(fundamentals(facade_poses(rng), wall_points(rng), 0.5, rng))
    found = self_calibrated(prior_intrinsics(), pairs, ReconstructionConfig())
    assert found.cameras[0].fx == found.cameras[0].fy == pytest.approx(FOCAL, rel=0.03)
    assert found.cameras[0].model == "simple-radial" and found.cameras[0].cx == (WIDTH - 1) / 2
    assert found.source == FOCAL_FROM_PAIRS and set(found.focal_sources) == {FOCAL_FROM_PAIRS}
    assert "fundamental matrices" in found.warnings[-1]
    for kept in (prior_intrinsics("exif"), prior_intrinsics(per_image=True)):
        assert self_calibrated(kept, pairs, ReconstructionConfig()) is kept
    switched_off = ReconstructionConfig(camera={"focal_from_pairs": False})
    assert self_calibrated(prior_intrinsics(), pairs, switched_off).cameras[0].fx == PRIOR
    # Pairs under verify_pair_min_inliers do not vote: none left, the prior stays.
    weak = geometries([g.F for g in pairs.values()], inliers=10)
    assert self_calibrated(prior_intrinsics(), weak, ReconstructionConfig()).cameras[0].fx == PRIOR


def test_the_pipeline_keeps_the_prior_where_the_pairs_do_not_determine_the_focal_length():
    rng = np.random.default_rng(2)
    pairs = geometries(fundamentals(ring_poses(), rng.uniform(-1, 1, (2000, 3)), 0.5, rng))
    initial = prior_intrinsics()
    assert self_calibrated(initial, pairs, ReconstructionConfig()) is initial
