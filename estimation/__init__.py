"""Structure from Motion: images in, cameras, points, COLMAP/PLY/transforms.json out.

`reconstruct` and `ReconstructionResult` load lazily (they pull in OpenCV and GTSAM), so importing
`estimation` for its configuration or errors stays cheap.
"""

from typing import TYPE_CHECKING

from estimation.config import ReconstructionConfig
from estimation.errors import DegenerateConfigurationError, InputError

if TYPE_CHECKING:
    from estimation.pipeline import ReconstructionResult, reconstruct

__all__ = [
    "DegenerateConfigurationError",
    "InputError",
    "ReconstructionConfig",
    "ReconstructionResult",
    "reconstruct",
]

_LAZY = {"reconstruct", "ReconstructionResult"}


def __getattr__(name: str) -> object:
    if name in _LAZY:
        from estimation import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'estimation' has no attribute {name!r}")
