"""Scene bounds and the similarity between a dataset's original frame and the normalized scene frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Bounds:
    """Ray bounds (near, far: distances along unit directions) and the axis-aligned box holding the scene.

    unbounded: the box is only the region of interest; content reaches out to `far` all around it (models
    that support this contract the space beyond the box, see neural.contraction).
    """

    near: float
    far: float
    scene_box_min: tuple[float, float, float]
    scene_box_max: tuple[float, float, float]
    unbounded: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.near < self.far:
            raise ValueError(f"Bounds needs 0 <= near < far, got near={self.near}, far={self.far}")
        if any(lo >= hi for lo, hi in zip(self.scene_box_min, self.scene_box_max, strict=True)):
            raise ValueError(f"Bounds box min {self.scene_box_min} must be below max {self.scene_box_max}")

    def to_dict(self) -> dict[str, Any]:
        return {
            "near": self.near,
            "far": self.far,
            "scene_box_min": list(self.scene_box_min),
            "scene_box_max": list(self.scene_box_max),
            "unbounded": self.unbounded,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Bounds:
        return cls(
            near=float(data["near"]),
            far=float(data["far"]),
            scene_box_min=tuple(float(v) for v in data["scene_box_min"]),
            scene_box_max=tuple(float(v) for v in data["scene_box_max"]),
            unbounded=bool(data.get("unbounded", False)),
        )


@dataclass(frozen=True)
class SceneNormalization:
    """x_scene = scale (x_original - centre): where the scene frame sits in the dataset's original frame."""

    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0

    def pose_to_scene(self, c2w_original: np.ndarray) -> np.ndarray:
        """Camera-to-world (4,4) or (N,4,4) in the original frame -> the scene frame (rotation unchanged)."""
        c2w = np.array(c2w_original, dtype=np.float64, copy=True)
        c2w[..., :3, 3] = self.scale * (c2w[..., :3, 3] - np.asarray(self.centre))
        return c2w

    def pose_to_original(self, c2w_scene: np.ndarray) -> np.ndarray:
        """Inverse of pose_to_scene."""
        c2w = np.array(c2w_scene, dtype=np.float64, copy=True)
        c2w[..., :3, 3] = c2w[..., :3, 3] / self.scale + np.asarray(self.centre)
        return c2w

    def points_to_scene(self, points: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(points, dtype=np.float64) - np.asarray(self.centre))

    def to_dict(self) -> dict[str, Any]:
        return {"centre": list(self.centre), "scale": self.scale}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SceneNormalization:
        return cls(centre=tuple(float(v) for v in data["centre"]), scale=float(data["scale"]))
