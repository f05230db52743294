"""Homography DLT in RANSAC, its transfer error, and the baseline it implies."""

import numpy as np
import pytest

from estimation.config import RansacConfig
from estimation.errors import DegenerateConfigurationError
from estimation.synthetic import rotation_about_axis
from estimation.two_view.homography import (
    _homography_rows,
    homography_dlt,
    homography_translation,
    ransac_homography,
    transfer_error,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
H_TRUE = np.array([[0.9, -0.1, 30.0], [0.12, 1.05, -12.0], [1e-4, -2e-4, 1.0]])


def mapped(H, uv):
    x = np.c_[uv, np.ones(len(uv))] @ H.T
    return x[:, :2] / x[:, 2:]


def test_the_dlt_recovers_h_from_four_exact_correspondences():
    uv1 = np.array([[10.0, 20.0], [600.0, 30.0], [580.0, 450.0], [40.0, 400.0]])
    H = homography_dlt(uv1, mapped(H_TRUE, uv1))
    np.testing.assert_allclose(H / H[2, 2], H_TRUE, rtol=1e-8, atol=1e-10)


def test_ransac_keeps_the_correspondences_h_maps_within_the_threshold():
    rng = np.random.default_rng(0)
    uv1 = rng.uniform([0, 0], [640, 480], (300, 2))
    uv2 = mapped(H_TRUE, uv1) + rng.normal(0, 0.5, (300, 2))
    outlier = rng.random(300) < 0.3
    uv2[outlier] += rng.uniform(20, 200, (outlier.sum(), 2)) * rng.choice([-1, 1], (outlier.sum(), 2))
    result = ransac_homography(uv1, uv2, 3.0, RansacConfig())
    np.testing.assert_array_equal(result.inlier_mask, ~outlier)
    assert np.median(transfer_error(result.H, uv1[~outlier], mapped(H_TRUE, uv1[~outlier]))) < 0.2
    with pytest.raises(DegenerateConfigurationError, match="homography needs at least 4"):
        ransac_homography(uv1[:3], uv2[:3], 3.0, RansacConfig())


def test_the_translation_of_a_rotation_homography_is_zero_and_of_a_plane_its_baseline_over_distance():
    R = rotation_about_axis([0.1, 1.0, 0.0], np.deg2rad(12))
    assert homography_translation(K @ R @ np.linalg.inv(K) * 3.0, K, K) < 1e-12
    t, n, d = np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 6.0     # plane z = 6
    plane = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
    assert homography_translation(plane, K, K) == pytest.approx(0.05, rel=0.05)


def test_homography_rows_vanish_on_h_for_exact_correspondences_batched_and_single():
    rng = np.random.default_rng(6)
    uv1 = rng.uniform(0, 640, (3, 7, 2))
    uv2 = np.stack([mapped(H_TRUE, uv) for uv in uv1])
    rows = _homography_rows(uv1, uv2)
    assert rows.shape == (3, 14, 9)
    np.testing.assert_allclose(rows @ H_TRUE.ravel(), 0.0, atol=1e-8)
    np.testing.assert_array_equal(_homography_rows(uv1[1], uv2[1]), rows[1])
