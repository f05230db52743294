"""Neural radiance fields: datasets, the paper's model and a fast grid model, training, rendering, evaluation.

The public API is imported lazily (attribute access triggers the import), so `import neural` is cheap
and does not load torch until a function is used.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_EXPORTS: dict[str, str] = {
    "TrainConfig": "neural.config",
    "Dataset": "neural.data",
    "load_dataset": "neural.data",
    "Bounds": "neural.bounds",
    "SceneNormalization": "neural.bounds",
    "TrainResult": "neural.training",
    "train": "neural.training",
    "render_view": "neural.inference",
    "render_orbit": "neural.inference",
    "load_run": "neural.inference",
    "EvalResult": "neural.evaluation",
    "ImageMetrics": "neural.evaluation",
    "evaluate": "neural.evaluation",
    "CheckpointInfo": "neural.checkpoints",
    "list_checkpoints": "neural.checkpoints",
    "DatasetError": "neural.errors",
    "CheckpointError": "neural.errors",
    "build_model": "neural.models",
}

__all__ = [
    "CheckpointError",
    "CheckpointInfo",
    "Dataset",
    "DatasetError",
    "EvalResult",
    "ImageMetrics",
    "Bounds",
    "SceneNormalization",
    "TrainConfig",
    "TrainResult",
    "build_model",
    "evaluate",
    "list_checkpoints",
    "load_dataset",
    "load_run",
    "render_orbit",
    "render_view",
    "train",
]

if TYPE_CHECKING:
    from neural.bounds import Bounds, SceneNormalization
    from neural.checkpoints import CheckpointInfo, list_checkpoints
    from neural.config import TrainConfig
    from neural.data import Dataset, load_dataset
    from neural.errors import CheckpointError, DatasetError
    from neural.evaluation import EvalResult, ImageMetrics, evaluate
    from neural.inference import load_run, render_orbit, render_view
    from neural.models import build_model
    from neural.training import TrainResult, train


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'neural' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value
