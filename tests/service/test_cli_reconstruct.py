"""`sfmnerf reconstruct`: the real Unity Hall data, and bad input as a one-line error with exit code 1."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from service.cli import main
from tests.service.conftest import capture_reconstruction_config


def run(*args: str):
    return CliRunner().invoke(main, ["reconstruct", *map(str, args)])


@pytest.mark.slow
def test_reconstruct_unity_hall_writes_every_output(shared_data, tmp_path):
    out = tmp_path / "out"
    result = run(shared_data / "unity_hall", "--out", out)
    assert result.exit_code == 0, result.output
    assert "registered 5/5 images" in result.output
    for stage in ["loading images", "reading match files", "writing outputs"]:
        assert stage in result.output  # one progress bar per stage
    bars = {line.split("  ")[0] for line in result.output.replace("\r", "\n").splitlines() if "%" in line}
    assert len(bars) >= 5  # ... the pipeline's stages included
    for name in [
        "sparse/cameras.txt",
        "sparse/images.txt",
        "sparse/points3D.txt",
        "points.ply",
        "transforms.json",
        "report.json",
        "figures/cameras_and_points_top_view.png",
    ]:
        assert (out / name).is_file(), name
    assert json.loads((out / "report.json").read_text())["features"]["source"] == "matches"


def copy(source: Path, target: Path, names: list[str]) -> Path:
    target.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(source / name, target / name)
    return target


def assert_clean_failure(result, *expected: str) -> None:
    assert result.exit_code != 0
    assert result.output.startswith("Error: ") or "\nError: " in result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    for text in expected:
        assert text in result.output


def test_a_folder_with_one_image_fails_with_a_message_naming_it(shared_data, tmp_path):
    folder = copy(shared_data / "unity_hall", tmp_path / "in", ["1.png", "calibration.txt"])
    assert_clean_failure(run(folder, "--out", tmp_path / "out"), str(folder), "at least 2")


def test_a_broken_match_row_fails_with_a_message_naming_file_and_line(shared_data, tmp_path):
    folder = copy(shared_data / "unity_hall", tmp_path / "in", ["1.png", "2.png", "calibration.txt"])
    (folder / "matching1.txt").write_text("2 1 2 3 10 20 2 30 40\n2 1 2 3 10 20 2 30\n")
    assert_clean_failure(
        run(folder, "--out", tmp_path / "out"), f"{folder / 'matching1.txt'}, line 2: truncated row"
    )


def test_a_singular_calibration_given_on_the_command_line_fails_naming_it(shared_data, tmp_path):
    folder = copy(shared_data / "unity_hall", tmp_path / "in", ["1.png", "2.png"])
    calibration = tmp_path / "K.txt"
    calibration.write_text("1 2 3\n2 4 6\n0 0 1\n")
    result = run(folder, "--out", tmp_path / "out", "--calibration", calibration, "--features", "sift")
    assert_clean_failure(result, f"{calibration}: K is singular")


@pytest.mark.parametrize(("option", "value"), [("--features", "orb"), ("--estimator", "cuda")])
def test_an_unknown_choice_is_a_usage_error_naming_the_option(shared_data, tmp_path, option, value):
    result = run(shared_data / "unity_hall", "--out", tmp_path / "out", option, value)
    assert result.exit_code == 2 and f"Invalid value for '{option}'" in result.output


@pytest.mark.parametrize(("arguments", "expected"), [
    ([], ("five-point", "numpy")),
    (["--relative-pose", "eight-point"], ("eight-point", "numpy")),
    (["--estimator", "opencv"], ("five-point", "opencv")),
])
def test_the_relative_pose_solver_and_its_ransac_are_chosen_on_the_command_line(
        monkeypatch, shared_data, tmp_path, arguments, expected):
    seen = capture_reconstruction_config(monkeypatch)
    assert_clean_failure(run(shared_data / "unity_hall", "--out", tmp_path / "out", *arguments), "stopped")
    assert [(config.two_view.relative_pose, config.two_view.estimator) for config in seen] == [expected]


@pytest.mark.parametrize(("arguments", "expected"),
                         [([], 0), (["--workers", "1"], 1), (["--workers", "3"], 3)])
def test_the_worker_count_is_chosen_on_the_command_line(monkeypatch, shared_data, tmp_path, arguments,
                                                        expected):
    seen = capture_reconstruction_config(monkeypatch)
    assert_clean_failure(run(shared_data / "unity_hall", "--out", tmp_path / "out", *arguments), "stopped")
    assert [config.sift.workers for config in seen] == [expected]
