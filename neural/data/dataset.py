"""The typed dataset every loader returns: posed images, splits, scene bounds.

Conventions: poses are camera-to-world (4,4) in OpenGL camera axes; intrinsics are pixels; images are
float32 RGB in [0,1].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neural.bounds import Bounds, SceneNormalization
from neural.errors import DatasetError

SPLITS: tuple[str, ...] = ("train", "val", "test")


@dataclass(frozen=True)
class DepthRays:
    """Rays of training photos with a known termination distance (a reconstruction's observed points).

    Pixel (u, v) as `neural.rays` indexes it (its centre at u + 1/2), continuous; distance along the unit
    ray from the camera centre and its std-dev, scene frame.
    """

    image: np.ndarray  # (O,) index into the dataset's images
    u: np.ndarray  # (O,)
    v: np.ndarray  # (O,)
    distance: np.ndarray  # (O,)
    sigma: np.ndarray  # (O,)

    def of_images(self, indices: np.ndarray) -> DepthRays:
        """The rays of these images only, their image index renumbered to the position in `indices`."""
        position = np.full(int(max(self.image.max(initial=0), np.max(indices, initial=0))) + 1, -1)
        position[indices] = np.arange(len(indices))
        keep = position[self.image] >= 0
        return DepthRays(position[self.image[keep]], self.u[keep], self.v[keep], self.distance[keep],
                         self.sigma[keep])


@dataclass
class Dataset:
    """Posed images of one scene with their split indices and scene bounds."""

    images: np.ndarray  # (N,H,W,3) float32 in [0,1]
    poses: np.ndarray  # (N,4,4) float32 camera-to-world, OpenGL axes, scene frame
    fx: float
    fy: float
    cx: float
    cy: float
    scene: Bounds
    splits: dict[str, np.ndarray]  # split name -> indices into images
    image_names: list[str]
    source: Path
    white_background: bool = True
    normalization: SceneNormalization = field(default_factory=SceneNormalization)
    depth_rays: DepthRays | None = None  # a reconstruction's depths.npz, if it has one

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def near(self) -> float:
        return self.scene.near

    @property
    def far(self) -> float:
        return self.scene.far

    def split(self, name: str) -> np.ndarray:
        """Indices of split `name`; DatasetError if it is absent or empty."""
        indices = self.splits.get(name)
        if indices is None or len(indices) == 0:
            have = ", ".join(f"{k} ({len(v)})" for k, v in self.splits.items())
            raise DatasetError(f"{self.source}: split {name!r} is empty or missing (splits: {have})")
        return indices
