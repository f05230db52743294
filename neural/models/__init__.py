"""Radiance models by name: "vanilla" (the NeRF paper's MLP), "fast" (a dense learned grid for CPUs) and
"tensorf" (a vector-matrix factorized grid)."""

from __future__ import annotations

import importlib
from typing import Any

from pydantic import BaseModel

from neural.config import ModelName
from neural.models.base import Bounds, RadianceModel, RayBundleOutput

#: name -> (module, model class, config class); modules are imported on demand, so the package works
#: (and imports quickly) whichever models are present.
MODEL_REGISTRY: dict[str, tuple[str, str, str]] = {
    "vanilla": ("neural.models.vanilla", "VanillaModel", "VanillaModelConfig"),
    "fast": ("neural.models.fast", "FastModel", "FastModelConfig"),
    "tensorf": ("neural.models.tensorf", "TensorVMModel", "TensorVMConfig"),
}
MODEL_NAMES: tuple[str, ...] = tuple(MODEL_REGISTRY)


def model_classes(name: str) -> tuple[type[RadianceModel], type[BaseModel]]:
    """The model class and its config class for a model name."""
    if name not in MODEL_REGISTRY:
        raise ValueError(f"unknown model {name!r}; choose one of {', '.join(MODEL_NAMES)}")
    module_name, model_name, config_name = MODEL_REGISTRY[name]
    module = importlib.import_module(module_name)
    return getattr(module, model_name), getattr(module, config_name)


def build_model(name: ModelName, scene: Bounds, **overrides: Any) -> RadianceModel:
    """The model `name` for `scene`, its config fields overridden by `overrides` (unknown ones are errors)."""
    model_type, config_type = model_classes(name)
    return model_type(scene, config_type(**overrides))


__all__ = [
    "MODEL_NAMES",
    "ModelName",
    "RadianceModel",
    "RayBundleOutput",
    "Bounds",
    "build_model",
    "model_classes",
]
