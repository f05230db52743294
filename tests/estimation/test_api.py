"""`estimation.reconstruct` end to end on the real Unity Hall data, its outputs, and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from estimation import InputError, ReconstructionConfig, reconstruct
from estimation.io.export import opencv_pose_to_opengl_c2w, read_colmap_text, read_ply
from estimation.synthetic import project

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def unity(shared_data, tmp_path_factory):
    """One reconstruction of Unity Hall shared by the tests below, with the progress it reported."""
    out_dir = tmp_path_factory.mktemp("unity_out")
    events: list[tuple[str, float]] = []
    result = reconstruct(shared_data / "unity_hall", out_dir,
                         progress=lambda stage, fraction: events.append((stage, fraction)))
    return result, events


def test_all_five_unity_hall_images_are_registered(unity):
    result, _ = unity
    assert result.report["images_total"] == 5
    assert result.report["images_registered"] == 5, result.report["unregistered"]
    assert sorted(result.model.poses) == [0, 1, 2, 3, 4]
    assert result.report["unregistered"] == []


def test_rms_reprojection_error_after_bundle_adjustment_is_below_one_pixel(unity):
    result, _ = unity
    after = result.report["reprojection_error_px"]["after_ba"]
    assert after["rms"] < 1.0
    assert after["median"] <= after["mean"] <= after["rms"]
    assert result.report["points"] >= 500


def test_the_exported_colmap_model_reproduces_the_reported_errors(unity):
    """Reading sparse/ back and reprojecting gives each point's error and the RMS in report.json."""
    result, _ = unity
    colmap = read_colmap_text(result.out_dir / "sparse")
    np.testing.assert_allclose(colmap.K, result.K)
    assert (colmap.width, colmap.height) == (800, 600)
    assert colmap.image_names == {index + 1: result.model.image_names[index] for index in result.model.poses}
    assert len(colmap.points) == result.report["points"]
    point_row = {point_id: row for row, point_id in enumerate(colmap.point_ids)}
    squared, per_point = [], [[] for _ in colmap.point_ids]
    for image_id, pose in colmap.poses.items():
        rows = np.array([point_row[p] for p in colmap.image_point_ids[image_id]])
        predicted = project(colmap.K, pose, colmap.points[rows])
        residual = np.linalg.norm(predicted - colmap.image_uv[image_id], axis=1)
        squared.extend(residual**2)
        for row, value in zip(rows, residual, strict=True):
            per_point[row].append(value)
    rms = float(np.sqrt(np.mean(squared)))
    assert rms == pytest.approx(result.report["reprojection_error_px"]["after_ba"]["rms"], rel=1e-6)
    np.testing.assert_allclose([np.mean(v) for v in per_point], colmap.errors, rtol=1e-6, atol=1e-9)


def test_ply_transforms_report_and_figures_are_written_and_loadable(unity):
    result, _ = unity
    out = result.out_dir
    points, colors = read_ply(out / "points.ply")
    assert len(points) == result.report["points"] and colors.dtype == np.uint8
    np.testing.assert_allclose(points, result.model.points, rtol=1e-6, atol=1e-6)

    transforms = json.loads((out / "transforms.json").read_text())
    assert (transforms["w"], transforms["h"]) == (800, 600)
    assert transforms["fl_x"] == pytest.approx(result.K[0, 0])
    assert len(transforms["frames"]) == result.report["images_registered"]
    for frame, (index, pose) in zip(transforms["frames"], sorted(result.model.poses.items()), strict=True):
        image = (out / frame["file_path"]).resolve()
        assert image.is_file() and image.name == result.model.image_names[index]
        np.testing.assert_allclose(frame["transform_matrix"], opencv_pose_to_opengl_c2w(pose), atol=1e-12)

    report = json.loads((out / "report.json").read_text())
    assert report == json.loads(json.dumps(result.report))
    for key in ["images_total", "images_registered", "unregistered", "points", "mean_track_length",
                "reprojection_error_px", "ransac_inliers_per_pair", "seconds_per_stage", "intrinsics",
                "cameras"]:
        assert key in report
    assert report["mean_track_length"] >= 2.0
    assert all(n > 0 for n in report["ransac_inliers_per_pair"].values())
    assert report["intrinsics"]["K"] == result.K.tolist()
    for camera in report["cameras"]:
        R, t, C = (np.array(camera[key]) for key in ("R", "t", "C"))
        np.testing.assert_allclose(C, -R.T @ t, atol=1e-9)

    for name in ["initial_pair_matches.png", "triangulation_linear_vs_nonlinear.png",
                 "cameras_and_points_top_view.png"]:
        with Image.open(out / "figures" / name) as figure:
            assert figure.format == "PNG" and min(figure.size) > 300


def test_the_visibility_matrix_has_every_point_in_two_or_more_registered_images(unity):
    result, _ = unity
    visibility = result.model.visibility
    assert visibility.shape == (result.report["points"], 5)
    assert visibility.sum(axis=1).min() >= 2
    assert not visibility[:, sorted(result.model.unregistered)].any()


def test_progress_is_reported_from_zero_to_one_in_order(unity):
    _, events = unity
    fractions = [fraction for _, fraction in events]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    assert all(b >= a - 1e-12 for a, b in zip(fractions, fractions[1:], strict=False))
    assert {"loading images", "reading match files", "finished"} <= {stage for stage, _ in events}


def copy_images(source: Path, target: Path, names: list[str]) -> Path:
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(source / name, target / name)
    return target


def test_a_folder_with_one_image_is_an_input_error(shared_data, tmp_path):
    folder = copy_images(shared_data / "unity_hall", tmp_path / "in", ["1.png", "calibration.txt"])
    with pytest.raises(InputError, match="at least 2"):
        reconstruct(folder, tmp_path / "out")


def test_asking_for_match_files_where_there_are_none_is_an_input_error(shared_data, tmp_path):
    folder = copy_images(shared_data / "unity_hall", tmp_path / "in", ["1.png", "2.png", "calibration.txt"])
    with pytest.raises(InputError, match="no matching"):
        reconstruct(folder, tmp_path / "out", ReconstructionConfig(features="matches"))


def test_a_missing_calibration_is_an_input_error_naming_the_file(shared_data, tmp_path):
    folder = copy_images(shared_data / "unity_hall", tmp_path / "in", ["1.png", "2.png"])
    with pytest.raises(InputError, match="calibration.txt: calibration file not found"):
        reconstruct(folder, tmp_path / "out")


def test_sift_features_also_register_all_unity_hall_images(shared_data, tmp_path):
    config = ReconstructionConfig(features="sift", write_figures=False)
    result = reconstruct(shared_data / "unity_hall", tmp_path, config)
    assert result.report["features"]["source"] == "sift"
    assert result.report["images_registered"] == 5, result.report["unregistered"]
    assert result.report["reprojection_error_px"]["after_ba"]["rms"] < 1.0
    assert not (tmp_path / "figures").exists()


def test_colmap_itself_loads_the_model_and_recomputes_the_same_point_errors(unity):
    """pycolmap (installed with the benchmarks' extra) reprojects with its own camera model and pixel
    convention; it must agree with the errors we wrote (this checks the +0.5 pixel shift too)."""
    pycolmap = pytest.importorskip("pycolmap")
    result, _ = unity
    reconstruction = pycolmap.Reconstruction(str(result.out_dir / "sparse"))
    assert reconstruction.num_reg_images() == result.report["images_registered"]
    assert reconstruction.num_points3D() == result.report["points"]
    written = {point_id: point.error for point_id, point in reconstruction.points3D.items()}
    reconstruction.update_point_3d_errors()
    for point_id, point in reconstruction.points3D.items():
        assert point.error == pytest.approx(written[point_id], abs=1e-6)
