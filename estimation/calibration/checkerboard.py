"""Camera calibration from photos of a checkerboard (Zhang's method, as OpenCV implements it).

Corners are found by findChessboardCorners on the photo downscaled to at most `max_detection_side`
pixels (fast, and robust to blur), mapped back to full size and refined there to sub-pixel accuracy
(cornerSubPix). The camera is
OpenCV's radial-tangential model with k1, k2, p1, p2 (k3 fixed at 0): the project's `opencv` camera.
Pixels follow the project's convention (centre of the top-left pixel at (0, 0), as OpenCV); MATLAB's
calibrator puts that centre at (1, 1), so its principal point is ours + 1.

Writes calibration.txt (the 3x3 K in the project's format), distortion.json (the camera with k1 k2 p1
p2, the RMS and per-image reprojection errors) and a figure of the detected corners.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from estimation.errors import InputError
from estimation.geometry.projection import Camera
from estimation.io.images import CALIBRATION_FILE_NAME, DISTORTION_FILE_NAME, list_images, load_rgb

CORNERS_FIGURE_NAME = "checkerboard_corners.png"
MIN_BOARDS = 3
"""Zhang's method needs three views of the plane for the five intrinsics (more for distortion)."""
MAX_DETECTION_SIDE = 1000
FIGURE_THUMBNAIL_WIDTH = 400
SUBPIX_WINDOW_FRACTION = 0.25
"""cornerSubPix's half window: this fraction of the smallest distance between neighbouring corners."""
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
DETECTION_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
CALIBRATION_FLAGS = cv2.CALIB_FIX_K3


class CheckerboardCalibration(NamedTuple):
    """The calibrated camera and how well it explains every detected corner."""

    camera: Camera                            # model opencv: fx fy cx cy k1 k2 p1 p2
    width: int
    height: int
    rms_px: float                             # over all corners of all used photos
    per_image_rms_px: dict[str, float]        # photo name -> RMS over its corners
    not_found: list[str]                      # photos where the board was not detected
    corners: dict[str, np.ndarray | None]     # photo name -> (N, 2) refined corners, None if not found


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): inner corners per row and per column; InputError otherwise."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts) or min(int(p) for p in parts) < 2:
        raise InputError(f"board {text!r}: expected COLSxROWS inner corners, e.g. 9x6 (each at least 2)")
    return int(parts[0]), int(parts[1])


def board_points(board: tuple[int, int], square_size: float) -> np.ndarray:
    """(N, 3) corners of the board in its own plane z = 0, row by row, in units of `square_size`."""
    columns, rows = board
    grid = np.mgrid[0:columns, 0:rows].T.reshape(-1, 2)
    return np.column_stack([grid * square_size, np.zeros(len(grid))]).astype(np.float32)


def detect_corners(gray: np.ndarray, board: tuple[int, int], max_detection_side: int = MAX_DETECTION_SIDE
                   ) -> np.ndarray | None:
    """(N, 2) sub-pixel inner corners of the board in full-size pixels, or None if not found."""
    scale = min(1.0, max_detection_side / max(gray.shape))
    small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else gray
    found, corners = cv2.findChessboardCorners(small, board, flags=DETECTION_FLAGS)
    if not found:
        return None
    # Map back: pixel centres scale about (-0.5, -0.5), the corner of the top-left pixel.
    corners = ((corners.reshape(-1, 2) + 0.5) / scale - 0.5).astype(np.float32)
    spacing = np.linalg.norm(np.diff(corners.reshape(board[1], board[0], 2), axis=1), axis=2).min()
    half_window = max(2, int(SUBPIX_WINDOW_FRACTION * spacing))
    refined = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).copy(), (half_window, half_window), (-1, -1),
                               SUBPIX_CRITERIA)
    return refined.reshape(-1, 2).astype(float)


def calibrate_checkerboard(folder: Path, board: tuple[int, int], square_size: float = 1.0,
                           max_detection_side: int = MAX_DETECTION_SIDE) -> CheckerboardCalibration:
    """K, k1 k2 p1 p2 = argmin sum ||pi(camera, R_i X_j + t_i) - corner_ij||^2 (cv2.calibrateCamera)
    over the photos of `folder` where the board is found; InputError naming them if fewer than 3."""
    images = list_images(folder, min_images=1)
    corners = {}
    for path in images.paths:
        gray = cv2.cvtColor(load_rgb(path), cv2.COLOR_RGB2GRAY)
        corners[path.name] = detect_corners(gray, board, max_detection_side)
    found = [name for name, uv in corners.items() if uv is not None]
    not_found = [name for name, uv in corners.items() if uv is None]
    if len(found) < MIN_BOARDS:
        raise InputError(
            f"{folder}: the {board[0]}x{board[1]} board was found in {len(found)} of {len(images)} photos "
            f"({', '.join(found) or 'none'}), need at least {MIN_BOARDS}; "
            f"not found in: {', '.join(not_found)}"
        )
    object_points = [board_points(board, square_size)] * len(found)
    image_points = [corners[name].astype(np.float32)[:, None] for name in found]
    _, K, distortion, rvecs, tvecs = cv2.calibrateCamera(
        object_points, image_points, (images.width, images.height), None, None, flags=CALIBRATION_FLAGS
    )
    k1, k2, p1, p2 = (float(v) for v in distortion.ravel()[:4])
    camera = Camera.from_K(K, model="opencv", k1=k1, k2=k2, p1=p1, p2=p2)
    per_image, squared = {}, []
    for name, points, rvec, tvec in zip(found, object_points, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(points, rvec, tvec, K, distortion)
        error = ((projected.reshape(-1, 2) - corners[name]) ** 2).sum(axis=1)
        per_image[name] = float(np.sqrt(error.mean()))
        squared.append(error)
    return CheckerboardCalibration(
        camera=camera, width=images.width, height=images.height,
        rms_px=float(np.sqrt(np.concatenate(squared).mean())), per_image_rms_px=per_image,
        not_found=not_found, corners=corners,
    )


def write_calibration(result: CheckerboardCalibration, folder: Path, out_dir: Path,
                      figure: bool = True) -> dict[str, Path]:
    """calibration.txt (K), distortion.json and the corners figure into out_dir; their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    K = result.camera.K
    paths = {"calibration": out_dir / CALIBRATION_FILE_NAME, "distortion": out_dir / DISTORTION_FILE_NAME}
    paths["calibration"].write_text("\n".join(" ".join(f"{v:.12g}" for v in row) for row in K) + "\n")
    paths["distortion"].write_text(json.dumps({
        "camera": result.camera.to_dict(), "width": result.width, "height": result.height,
        "pixel_convention": "centre of the top-left pixel at (0, 0) (OpenCV); MATLAB's is (1, 1)",
        "rms_px": result.rms_px, "per_image_rms_px": result.per_image_rms_px,
        "board_not_found": result.not_found,
    }, indent=2) + "\n")
    if figure:
        from estimation.io.figures import plot_checkerboard_corners  # matplotlib is only needed here

        names = list(result.corners)
        titles = [f"{name}: RMS {result.per_image_rms_px[name]:.2f} px" if name in result.per_image_rms_px
                  else f"{name}: board not found" for name in names]
        scale = min(1.0, FIGURE_THUMBNAIL_WIDTH / result.width)
        thumbnails = [cv2.resize(load_rgb(Path(folder) / name), None, fx=scale, fy=scale,
                                 interpolation=cv2.INTER_AREA) for name in names]
        corners = [None if result.corners[n] is None else (result.corners[n] + 0.5) * scale - 0.5
                   for n in names]
        paths["figure"] = plot_checkerboard_corners(thumbnails, corners, titles,
                                                    out_dir / CORNERS_FIGURE_NAME)
    return paths
