"""Data shared by every step of the SfM pipeline, with its conventions named once.

Conventions (used everywhere in `estimation/`):
- Poses are world-to-camera: x_cam = R @ X_world + t. The camera centre is C = -R.T @ t.
- Camera axes are OpenCV's: +x right, +y down, +z forward (looking direction).
- `uv` are pixel coordinates (origin at the top-left pixel's corner is *not* assumed; they are
  whatever the match file or SIFT gives, the same convention K was calibrated in).
  "Normalized" coordinates are K^-1 [u, v, 1].
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

ProgressCallback = Callable[[str, float], None]
"""progress(stage_name, overall_fraction_in_0_1)."""


@dataclass(frozen=True)
class CameraPose:
    """World-to-camera rotation R (3x3) and translation t (3,): x_cam = R X + t."""

    R: np.ndarray
    t: np.ndarray

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, C = -R^T t."""
        return -self.R.T @ self.t

    @staticmethod
    def from_center(R: np.ndarray, C: np.ndarray) -> CameraPose:
        """Pose from rotation and camera centre: t = -R C."""
        return CameraPose(R=np.asarray(R, float), t=-np.asarray(R, float) @ np.asarray(C, float))

    def projection_matrix(self, K: np.ndarray) -> np.ndarray:
        """P = K [R | t] (3x4)."""
        return K @ np.hstack([self.R, self.t[:, None]])


@dataclass(frozen=True)
class Tracks:
    """Multi-view feature tracks: each track is one physical point seen in two or more images.

    Observations are stored flat: observation o says track `track_index[o]` is seen in image
    `image_index[o]` at pixel `uv[o]`. A track appears at most once per image.
    """

    image_names: list[str]          # image index -> file name (e.g. "1.png")
    track_index: np.ndarray         # (O,) int
    image_index: np.ndarray         # (O,) int
    uv: np.ndarray                  # (O, 2) float pixel coordinates
    colors: np.ndarray              # (T, 3) uint8 RGB per track

    @property
    def num_tracks(self) -> int:
        return int(self.colors.shape[0])

    def pair_correspondences(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tracks seen in both images i and j: (track ids, uv in i (K,2), uv in j (K,2))."""
        in_i = self.image_index == i
        in_j = self.image_index == j
        ti, tj = self.track_index[in_i], self.track_index[in_j]
        common, ai, aj = np.intersect1d(ti, tj, assume_unique=True, return_indices=True)
        return common, self.uv[in_i][ai], self.uv[in_j][aj]
