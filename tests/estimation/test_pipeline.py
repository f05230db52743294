"""`estimation.reconstruct` end to end on the real Unity Hall data, its outputs, and bad input."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import ExifTags, Image

from estimation import InputError, ReconstructionConfig, reconstruct
from estimation.bundle_adjustment.factor_graph import IntrinsicsRefinement
from estimation.config import CameraConfig
from estimation.io.export import opencv_pose_to_opengl_c2w, read_colmap_text, read_depths, read_ply
from estimation.io.images import find_calibration, find_distortion, list_images
from estimation.mapper.verification import FOLDED, MIRROR_AMBIGUITY
from estimation.pipeline import (
    SIDES_CONFLICTED,
    FeatureTracks,
    initial_intrinsics,
    model_summary,
    run_again,
    with_alternatives,
)
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
                "reprojection_error_px", "shared_tracks_per_pair", "seconds_per_stage", "intrinsics",
                "cameras"]:
        assert key in report
    assert report["mean_track_length"] >= 2.0
    assert all(n > 0 for n in report["shared_tracks_per_pair"].values())
    assert report["intrinsics"]["K"] == result.K.tolist()
    for camera in report["cameras"]:
        R, t, C = (np.array(camera[key]) for key in ("R", "t", "C"))
        np.testing.assert_allclose(C, -R.T @ t, atol=1e-9)

    for name in ["initial_pair_matches.png", "triangulation_linear_vs_nonlinear.png",
                 "cameras_and_points_top_view.png"]:
        with Image.open(out / "figures" / name) as figure:
            assert figure.format == "PNG" and min(figure.size) > 300


def test_each_model_in_the_report_carries_its_own_warnings(unity, shared_data):
    """A model left apart says why in report.json (`models[k].warnings`: a refused merge's reason)."""
    result, _ = unity
    apart = dataclasses.replace(result.model, warnings=["not merged into the largest model: 12% overlap"])
    summary = model_summary(list_images(shared_data / "unity_hall"), apart)
    assert summary["warnings"] == ["not merged into the largest model: 12% overlap"]
    assert result.report["models"][0]["warnings"] == result.model.warnings


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


def test_a_named_calibration_file_that_is_missing_is_an_input_error_naming_it(shared_data, tmp_path):
    folder = copy_images(shared_data / "unity_hall", tmp_path / "in", ["1.png", "2.png"])
    with pytest.raises(InputError, match="nothing.txt: calibration file not found"):
        reconstruct(folder, tmp_path / "out", ReconstructionConfig(calibration=tmp_path / "nothing.txt"))


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


# --- photos without calibration -------------------------------------------------------------------

def jpegs_with_exif(folder: Path, focal_35mm: float | None, count: int = 3) -> Path:
    """`count` 120x80 JPEGs whose EXIF says FocalLengthIn35mmFilm = focal_35mm (none when None)."""
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(count):
        exif = Image.Exif()
        if focal_35mm is not None:
            exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = focal_35mm
        Image.fromarray(np.full((80, 120, 3), 40 * k, np.uint8)).save(folder / f"{k}.jpg", exif=exif)
    return folder


def test_the_exif_focal_length_starts_a_shared_simple_radial_camera_at_the_image_centre(tmp_path):
    folder = jpegs_with_exif(tmp_path, focal_35mm=35)
    initial = initial_intrinsics(list_images(folder), None, CameraConfig())
    camera = initial.cameras[0]
    assert initial.source == "exif" and initial.warnings == []
    assert camera.model == "simple-radial"
    assert camera.fx == pytest.approx(35 / np.hypot(36, 24) * np.hypot(120, 80))
    assert (camera.cx, camera.cy) == (59.5, 39.5)      # pixel centres at integers: the centre is (w-1)/2
    # the principal point is refined from the centre for a shared camera (kept if significant)
    assert initial.refine == IntrinsicsRefinement(focal=True, distortion=True, per_image=False,
                                                  principal_point=True)


def test_exif_that_lies_falls_back_to_the_prior_with_a_warning_in_the_log(tmp_path, caplog):
    folder = jpegs_with_exif(tmp_path, focal_35mm=1)      # a 174 degree field of view
    with caplog.at_level("WARNING"):
        initial = initial_intrinsics(list_images(folder), None, CameraConfig(model="radial"))
    assert initial.source == "prior"
    assert initial.cameras[0].fx == pytest.approx(1.2 * 120)
    assert any("0.jpg: EXIF focal length ignored" in w and "absurd field of view" in w
               for w in initial.warnings)
    assert any("focal length prior 1.2 * max(width, height) = 144.0 px" in w for w in initial.warnings)
    assert "focal length prior" in caplog.text


def test_a_calibration_file_wins_over_exif_and_is_held_fixed(tmp_path):
    folder = jpegs_with_exif(tmp_path, focal_35mm=35)
    K = np.array([[100.0, 0, 60], [0, 101.0, 40], [0, 0, 1]])
    initial = initial_intrinsics(list_images(folder), K, CameraConfig())
    assert initial.source == "calibration file"
    np.testing.assert_array_equal(initial.cameras[0].K, K)
    assert not initial.refine.focal
    per_image = initial_intrinsics(list_images(folder), None, CameraConfig(single_camera=False))
    assert per_image.refine.per_image and len(set(map(id, per_image.cameras))) == 3
    assert not per_image.refine.principal_point          # held at the centre for per-image cameras


def test_unity_hall_without_calibration_registers_every_image_and_exports_the_refined_camera(
        shared_data, tmp_path):
    folder = copy_images(shared_data / "unity_hall", tmp_path / "in",
                         [*(f"{i}.png" for i in range(1, 6)), *(f"matching{i}.txt" for i in range(1, 5))])
    result = reconstruct(folder, tmp_path / "out", ReconstructionConfig(write_figures=False))
    report = result.report
    assert report["images_registered"] == 5
    assert report["intrinsics"]["source"] == "prior" and "focal length prior" in report["warnings"][0]
    camera = report["intrinsics"]["camera"]
    # From the 960 px prior (+81 %) to within 10 % of the checkerboard calibration's 531 px: five views
    # and a principal point held at the image centre, 14 px from the calibrated one, leave the focal
    # length loosely determined (measured: 498 px).
    assert camera["fx"] == pytest.approx(531.3, rel=0.10)
    assert report["reprojection_error_px"]["after_ba"]["rms"] < 0.6
    line = [row for row in (tmp_path / "out" / "sparse" / "cameras.txt").read_text().splitlines()
            if not row.startswith("#")][0].split()
    assert line[1] == "SIMPLE_RADIAL"
    np.testing.assert_allclose([float(v) for v in line[4:]],
                               [camera["fx"], camera["cx"] + 0.5, camera["cy"] + 0.5, camera["k1"]])
    transforms = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert (transforms["fl_x"], transforms["k1"], transforms["k2"]) == (camera["fx"], camera["k1"], 0.0)
    colmap = read_colmap_text(tmp_path / "out" / "sparse")
    assert colmap.cameras[1].model == "simple-radial"


def test_the_distortion_json_of_sfmnerf_calibrate_comes_with_its_calibration_and_is_held(tmp_path):
    folder = jpegs_with_exif(tmp_path, focal_35mm=None)
    (folder / "calibration.txt").write_text("100 0 60\n0 101 40\n0 0 1\n")
    coefficients = {"k1": -0.1, "k2": 0.02, "p1": 1e-3, "p2": -2e-3}
    (folder / "distortion.json").write_text(json.dumps({"camera": {"model": "opencv", **coefficients}}))
    initial = initial_intrinsics(list_images(folder), find_calibration(folder), CameraConfig(),
                                 find_distortion(folder))
    camera = initial.cameras[0]
    assert camera.model == "opencv" and initial.source == "calibration file and distortion.json"
    assert (camera.k1, camera.k2, camera.p1, camera.p2) == tuple(coefficients.values())
    assert not initial.refine.refines("opencv")
    (folder / "distortion.json").write_text("{}")
    with pytest.raises(InputError, match=r"distortion.json: expected the distortion.json of `sfmnerf"):
        find_distortion(folder)


@pytest.mark.parametrize(("seed", "max_mean_deg"), [(0, 0.32), (7, 0.5)])   # 0.28 and 0.42 measured
def test_no_camera_of_the_sparse_lego_ring_is_registered_in_the_wrong_place(shared_data, tmp_path, seed,
                                                                            max_mean_deg):
    """lego_ring_400: 50 views around a symmetric object; the weakly supported registrations used to put
    r_12 and r_28 on the far side of the ring (172-176 deg off) and r_34 6 deg off. Refused, they are
    registered later by guided matching (r_34) or in a second model that the merge moves into the first.
    With RANSAC seed 7, r_34 registered from 13 inliers that pinned its rotation only to 4.4 deg, 8 deg
    off, and 8 later views followed it 6-9 deg off; poses pinned that loosely are now refused (and listed
    in report.json's registration_checks) until more points pin them."""
    from estimation.geometry.alignment import aligned_pose_errors
    from estimation.types import CameraPose

    folder = shared_data / "lego_ring_400"
    result = reconstruct(folder, tmp_path, ReconstructionConfig(write_figures=False, ransac={"seed": seed}))
    truth = json.loads((folder / "ground_truth.json").read_text())["cameras"]
    names = result.model.image_names
    registered = sorted(result.model.poses)
    errors = aligned_pose_errors([result.model.poses[m] for m in registered],
                                 [CameraPose(np.array(truth[names[m]]["R"]), np.array(truth[names[m]]["t"]))
                                  for m in registered])
    assert errors.rotation_deg.max() < 5.0
    assert len(registered) >= 48
    assert errors.rotation_deg.mean() < max_mean_deg    # COLMAP: 0.37 over the 35 it registers
    report = json.loads((tmp_path / "report.json").read_text())
    model = report["models"][0]
    assert all("images merged" in merge for merge in model["merged_models"])
    assert model["merged_models"] or model["guided_registrations"]
    assert {"registration_checks", "unregistered"} <= report.keys()
    limit = ReconstructionConfig().mapper.verify_max_rotation_std_deg
    assert 0 < max(model["registration_rotation_std_deg"].values()) <= limit
    if seed == 7:   # the loose poses are refused, and the report says so (r_88: 12 inliers, 4.6 deg)
        assert any("rotation only to" in check["reason"] for check in report["registration_checks"])
    assert len(report["unregistered"]) == 50 - len(registered)
    assert all(entry["reason"] for entry in report["unregistered"])


def test_the_depths_file_holds_every_observation_with_its_sigma_along_the_ray(unity):
    result, _ = unity
    depths = read_depths(result.out_dir / "depths.npz")
    transforms = json.loads((result.out_dir / "transforms.json").read_text())
    assert depths.file_paths == [frame["file_path"] for frame in transforms["frames"]]
    model = result.model
    assert len(depths.frame) == len(model.obs_point)
    np.testing.assert_allclose(depths.point, model.points[model.obs_point])
    # Well-triangulated points of an 800 px capture: millimetres to centimetres of a scene metres across.
    scene_size = np.ptp(model.points, axis=0).max()
    assert 0 < np.median(depths.sigma) < 0.01 * scene_size
    # The per-axis noise: the residuals' RMS per axis, enlarged by the degrees of freedom the BA fitted.
    rms = result.report["reprojection_error_px"]["after_ba"]["rms"]
    residuals, free = 2 * len(model.obs_point), 6 * len(model.poses) + 3 * len(model.points) - 7
    assert depths.pixel_sigma == pytest.approx(rms * np.sqrt(residuals / 2 / (residuals - free)), rel=0.02)


@pytest.fixture(scope="module")
def look_alike_box():
    """A rendered ring of 20 views (256 px) around a box whose opposite sides carry one texture each: every
    view has a look-alike twin half a turn away, and those pairs verify."""
    from estimation.synthetic import render_box_ring

    return render_box_ring(num_views=20, size=256, seed=1)


def reconstructed_box(ring, folder: Path, calibrated: bool, progress=None):
    for k, rgb in enumerate(ring.images):
        Image.fromarray(rgb).save(folder / f"view_{k:03d}.png")
    if calibrated:
        np.savetxt(folder / "calibration.txt", ring.K)
    return reconstruct(folder, folder / "out", ReconstructionConfig(write_figures=False), progress=progress)


def assert_in_place_without_look_alike_neighbours(result, ring, twin_share: float = 0.75) -> None:
    """Every registered camera within 5 deg of the truth (18 of 20 or more), and the pairs left out as
    look-alikes mostly (over twin_share) the twins half a turn apart, with wrong Es of pairs far apart;
    never true neighbours (18-40 deg apart)."""
    from estimation.geometry.alignment import aligned_pose_errors, relative_pose, rotation_angle_deg

    registered = sorted(result.model.poses)
    errors = aligned_pose_errors([result.model.poses[m] for m in registered],
                                 [ring.poses[m] for m in registered])
    assert len(registered) >= 18 and errors.rotation_deg.max() < 5.0
    names = list(result.model.image_names)
    look_alikes = [pair.split("|") for pair in result.report["features"]["look_alike_pairs"]]
    apart_deg = np.array([rotation_angle_deg(np.eye(3), relative_pose(ring.poses[names.index(a)],
                                                                     ring.poses[names.index(b)]).R)
                          for a, b in look_alikes])
    assert len(apart_deg) >= 10 and np.mean(apart_deg > 135.0) > twin_share and apart_deg.min() > 45.0
    assert not any(warning.startswith(FOLDED) for warning in result.report["warnings"])


def test_a_box_whose_opposite_sides_look_alike_is_reconstructed_without_folding_onto_itself(
        tmp_path, look_alike_box):
    """The look-alike pairs' matches in the tracks folded the model (the far side's cameras at the near
    side's viewpoints, 175-180 deg off: checked with `two_view.max_rotation_residual_deg: null`); with
    calibration.txt they are left out before the tracks are built, and every camera is in place."""
    result = reconstructed_box(look_alike_box, tmp_path, calibrated=True)
    assert_in_place_without_look_alike_neighbours(result, look_alike_box)
    assert result.report["features"]["look_alike_check"] == "calibration file"


def test_without_calibration_a_folded_box_is_run_again_under_its_refined_camera(tmp_path, look_alike_box):
    """Without calibration.txt the look-alikes are not looked for up front (under the focal length prior the
    pairs' rotations cannot tell them): the first model folds. Under its refined focal length they are
    found, and the growing model has adopted them; run again under its refined camera (E verification, the
    look-alikes left out of the tracks), every camera is in place, and that model replaces the folded one."""
    reports = []
    result = reconstructed_box(look_alike_box, tmp_path, calibrated=False,
                               progress=lambda stage, fraction: reports.append((stage, fraction)))
    assert_in_place_without_look_alike_neighbours(result, look_alike_box)
    fractions = [fraction for _, fraction in reports]
    assert fractions == sorted(fractions) and any("(again, under" in stage for stage, _ in reports)
    check = result.report["features"]["look_alike_check"]
    # Found while the first model grew, which stopped it.
    assert "where its mapping stopped" in check
    assert check.endswith("folded; run again under its refined camera, which replaced it")
    adopted, between = map(int, re.search(r"(\d+) of the (\d+) between its images adopted", check).groups())
    assert adopted >= ReconstructionConfig().mapper.fold_min_pairs and 2 * adopted >= between
    assert result.report["seconds_per_stage"]["look-alike check"] > 0
    # Left out, the look-alikes vote on no registration and join no track.
    left_out = set(result.report["features"]["look_alike_pairs"])
    assert not left_out & set(result.report["features"]["two_view_geometry_per_pair"])
    assert all(result.report["features"]["verified_matches_per_pair"][pair] == 0 for pair in left_out)
    assert result.report["intrinsics"]["source"] == "prior"


class ClosingTracks:
    """Stands for the FeatureTracks of a front end: whether its worker processes were ended."""

    closed = False
    look_alikes = None     # no look-alike check, so none conflicted

    def close(self) -> None:
        self.closed = True


def test_a_run_again_that_builds_no_model_gives_none_and_ends_its_front_ends_workers():
    from estimation.errors import DegenerateConfigurationError
    from estimation.geometry.projection import Camera

    camera = Camera("simple-radial", fx=200.0, fy=200.0, cx=99.5, cy=99.5)
    front_ends, seen_K = [], []

    def extract(K, alternative):
        seen_K.append(K)
        front_ends.append(ClosingTracks())
        return front_ends[-1]

    def no_model(tracks, start):
        raise DegenerateConfigurationError("no initial pair")

    assert run_again(extract, no_model, camera) is None
    assert front_ends[-1].closed
    np.testing.assert_allclose(seen_K[-1], camera.pinhole().K)        # verified under the refined camera
    rerun = run_again(extract, lambda tracks, start: ("model",), camera)
    assert rerun.models == ("model",) and rerun.features is front_ends[-1] and not front_ends[-1].closed


def conflicted_tracks(names: list[str]) -> tuple[FeatureTracks, ClosingTracks]:
    """Tracks whose look-alike check conflicted (image 0 and 1's strongest pair against (1, 2): the
    alternatives leave out (1, 2), or (0, 1) and (0, 2)), and the stand-in for their planarity tests' worker
    processes, which says whether they were ended."""
    from estimation.features.view_graph import LookAlikes
    from estimation.types import Tracks

    tracks = Tracks(names, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3), np.uint8))
    workers = ClosingTracks()
    look_alikes = LookAlikes([], np.zeros(0), [(0, 1)], (((1, 2),), ((0, 1), (0, 2))))
    return FeatureTracks(tracks, "sift", {}, pair_types=workers, look_alikes=look_alikes), workers


def mapping(registered: int, folded: bool = False, mirrored: bool = False):
    """Stands for a mapping's models: the largest's registered images, its fold warning and its near-mirror
    warning."""
    from types import SimpleNamespace

    warnings = ([f"{FOLDED}: 3 pairs of cameras placed within 5 deg of one viewpoint"] if folded else []) + (
        [f"{MIRROR_AMBIGUITY}: 1 image(s) matched a pose on the other side"] if mirrored else [])
    return (SimpleNamespace(poses=dict.fromkeys(range(registered)), warnings=warnings),)


@pytest.mark.parametrize(("first", "second", "third", "kept"), [
    (mapping(2), mapping(3), mapping(2), 1),
    (mapping(3), mapping(3), mapping(3), 0),                      # a tie keeps the earlier
    (mapping(3), mapping(2), None, 0),                           # None: no model
    (mapping(2), mapping(3, folded=True), mapping(3), 2),        # a folded ring may register every view
    (mapping(3, folded=True), mapping(2), mapping(2), 1),
    (mapping(2), mapping(3, mirrored=True), mapping(3), 2),      # a tie: the one tried on no other side
])
def test_of_the_mappings_with_each_alternative_left_out_the_unfolded_one_that_registers_most_is_kept(
        first, second, third, kept):
    from estimation.errors import DegenerateConfigurationError

    names = ["a.png", "b.png", "c.png"]
    features, workers = conflicted_tracks(names)
    alternatives = [conflicted_tracks(names) for _ in range(2)]
    models = {id(alternatives[0][0]): second, id(alternatives[1][0]): third}

    def mapped(tracks):
        if models[id(tracks)] is None:
            raise DegenerateConfigurationError("no initial pair")
        return models[id(tracks)]

    resolved = with_alternatives(features, first, 1.5, lambda k: alternatives[k][0], mapped)
    assert resolved.models is (first, second, third)[kept]
    # Every discarded front end's workers are ended, the kept one's are left to the caller.
    assert [front_end.closed for front_end in (workers, *(w for _, w in alternatives))] == [
        k != kept for k in range(3)]
    outcome = resolved.features.details["look_alike_conflicts_outcome"]
    assert outcome.startswith("strongest pairs conflicted (a.png|b.png): mapped with every pair, "
                              f"{len(first[0].poses)} images registered")
    assert "with the 1 pairs that contradict them left out, " in outcome
    assert "with the 2 pairs that the rotations averaged over them put on other sides left out, " in outcome
    assert outcome.endswith(f"the {('first', 'second', 'third')[kept]} kept")
    assert (resolved.discarded_seconds >= 1.5) == (kept != 0)
    # Whichever is kept, the sides may be confused, and it says so.
    assert resolved.models[0].warnings[-1].startswith(SIDES_CONFLICTED)
    assert outcome in resolved.models[0].warnings[-1]


def test_a_sparse_box_ring_whose_strongest_pairs_conflict_is_mapped_each_way_and_kept_in_place(tmp_path):
    """20 views at 400 px: a look-alike beats the link that closes the ring, the check's strongest pairs
    conflict and nothing is left out; mapped so, the model folds (16 of 20, the far side half a turn off).
    With the conflicting link kept and the pairs that contradict it left out, every view registers in
    place, and that model is kept (the third way, with the look-alike kept instead, folds). Those pairs are
    views at least 45 deg apart, most of them twins (three in four; the rest near-twins whose E took the
    look-alike's rotation)."""
    from estimation.synthetic import render_box_ring

    ring = render_box_ring(num_views=20, size=400, seed=1)
    reports = []
    result = reconstructed_box(ring, tmp_path, calibrated=True,
                               progress=lambda stage, fraction: reports.append((stage, fraction)))
    assert_in_place_without_look_alike_neighbours(result, ring, twin_share=0.5)
    assert len(result.model.poses) == 20
    features = result.report["features"]
    assert features["look_alike_conflicts"]
    outcome = features["look_alike_conflicts_outcome"]
    first = int(re.search(r"every pair, (\d+) images registered", outcome).group(1))
    second = int(re.search(r"contradict them left out, (\d+) images registered", outcome).group(1))
    assert first < second == 20 and outcome.endswith("the second kept")
    fractions = [fraction for _, fraction in reports]
    assert fractions == sorted(fractions)
    assert any("(again, with other look-alikes left out)" in stage for stage, _ in reports)
    assert result.report["seconds_per_stage"]["look-alike check"] > 0
    assert any(warning.startswith(SIDES_CONFLICTED) for warning in result.report["warnings"])


def test_a_folded_box_whose_run_again_builds_no_model_keeps_its_first_model_in_full_and_warns(
        tmp_path, look_alike_box, monkeypatch):
    """When the run again after a fold does no better (here: it builds no model), the first model is kept:
    mapped in full, since the probe stopped it, and its warnings say it is folded."""
    import estimation.pipeline as pipeline

    monkeypatch.setattr(pipeline, "run_again", lambda extract, mapped, camera: None)
    result = reconstructed_box(look_alike_box, tmp_path, calibrated=False)
    check = result.report["features"]["look_alike_check"]
    assert "where its mapping stopped" in check and check.endswith("no model: the first model kept")
    assert len(result.model.poses) >= 15                   # the whole first model, not the stopped one
    assert any(warning.startswith(FOLDED) for warning in result.report["warnings"])
    assert result.report["features"]["look_alike_pairs"] == []     # the first front end's: none left out
