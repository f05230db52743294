"""Checkerboard calibration: rendered boards with a known camera, the real Unity Hall boards against
MATLAB's calibration, and the error when too few boards are found."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from estimation.calibration.checkerboard import board_points, calibrate_checkerboard, parse_board
from estimation.errors import InputError
from estimation.synthetic import rotation_about_axis
from service.cli import main

BOARD = (9, 6)
SQUARE_PX = 24          # texture pixels per square
MARGIN_PX = 30          # white border around the 10x7 squares
TRUE_K = np.array([[500.0, 0.0, 319.5], [0.0, 505.0, 239.5], [0.0, 0.0, 1.0]])
MATLAB_K = np.array([[531.122155322710, 0.0, 407.192550839899], [0.0, 531.541737503901, 313.308715048366],
                     [0.0, 0.0, 1.0]])
"""../shared/data/unity_hall_calibration/README.md: MATLAB R2022a, pixel centres at 1-based integers."""


def board_texture() -> np.ndarray:
    squares = (np.add.outer(np.arange(BOARD[1] + 1), np.arange(BOARD[0] + 1)) % 2 == 0)
    texture = np.kron(np.where(squares, 0, 255), np.ones((SQUARE_PX, SQUARE_PX))).astype(np.uint8)
    return np.pad(texture, MARGIN_PX, constant_values=255)


def render_board(R: np.ndarray, t: np.ndarray, size=(640, 480)) -> np.ndarray:
    """The board seen by TRUE_K at pose (R, t); board corner (i, j) is at (i, j, 0) in square units."""
    # texture pixel (centre convention) of board point (X, Y): X * SQUARE_PX + first inner corner
    first_corner = MARGIN_PX + SQUARE_PX - 0.5
    board_from_texture = np.linalg.inv(np.array([[SQUARE_PX, 0, first_corner], [0, SQUARE_PX, first_corner],
                                                 [0, 0, 1.0]]))
    H = TRUE_K @ np.column_stack([R[:, 0], R[:, 1], t]) @ board_from_texture
    image = cv2.warpPerspective(board_texture(), H, size, flags=cv2.INTER_LINEAR, borderValue=255)
    return np.repeat(image[:, :, None], 3, axis=2)


def write_rendered_boards(folder: Path, count: int, blank: tuple[int, ...] = ()) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for k in range(count):
        axis = np.array([np.cos(k), np.sin(k), 0.0])
        R = rotation_about_axis(axis, np.deg2rad(25 + 10 * rng.random())) @ rotation_about_axis(
            np.array([0, 0, 1.0]), rng.uniform(-0.3, 0.3))
        board_centre = np.array([(BOARD[0] - 1) / 2, (BOARD[1] - 1) / 2, 0.0])
        t = -R @ board_centre + np.array([*rng.uniform(-1.0, 1.0, 2), 16.0])
        pixels = np.full((480, 640, 3), 255, np.uint8) if k in blank else render_board(R, t)
        Image.fromarray(pixels).save(folder / f"{k + 1}.png")
    return folder


def test_board_text_and_points():
    assert parse_board("9x6") == (9, 6)
    with pytest.raises(InputError, match="expected COLSxROWS"):
        parse_board("9by6")
    points = board_points((3, 2), 2.0)
    np.testing.assert_array_equal(points[:4], [[0, 0, 0], [2, 0, 0], [4, 0, 0], [0, 2, 0]])


def test_rendered_boards_give_back_the_camera_that_rendered_them(tmp_path):
    result = calibrate_checkerboard(write_rendered_boards(tmp_path, 6), BOARD)
    assert result.not_found == []
    np.testing.assert_allclose(result.camera.K, TRUE_K, rtol=0.005, atol=1.0)
    assert abs(result.camera.k1) < 0.02 and result.rms_px < 0.2


def test_too_few_boards_is_an_error_naming_where_they_were_found(tmp_path):
    folder = write_rendered_boards(tmp_path, 3, blank=(1,))
    expected = "the 9x6 board was found in 2 of 3 photos (1.png, 3.png), need at least 3; not found in: 2.png"
    with pytest.raises(InputError, match=re.escape(expected)):
        calibrate_checkerboard(folder, BOARD)
    outcome = CliRunner().invoke(main, ["calibrate", str(folder), "--board", "9x6"])
    assert outcome.exit_code != 0 and expected in outcome.output


@pytest.mark.slow
def test_the_unity_hall_boards_agree_with_matlab(shared_data, tmp_path):
    outcome = CliRunner().invoke(main, ["calibrate", str(shared_data / "unity_hall_calibration"),
                                        "--board", "9x6", "--out", str(tmp_path)])
    assert outcome.exit_code == 0, outcome.output
    K = np.loadtxt(tmp_path / "calibration.txt")
    assert K[0, 0] == pytest.approx(MATLAB_K[0, 0], rel=0.01)
    assert K[1, 1] == pytest.approx(MATLAB_K[1, 1], rel=0.01)
    # MATLAB's pixel centres are 1-based: its principal point is ours + 1.
    np.testing.assert_allclose(K[:2, 2] + 1.0, MATLAB_K[:2, 2], atol=5.0)
    distortion = json.loads((tmp_path / "distortion.json").read_text())
    assert distortion["camera"]["model"] == "opencv"
    assert len(distortion["per_image_rms_px"]) >= 12 and distortion["rms_px"] < 1.0
    assert (tmp_path / "checkerboard_corners.png").stat().st_size > 10_000
