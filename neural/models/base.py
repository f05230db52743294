"""What every radiance model offers the trainer and the renderer, and what it knows about the scene."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from pydantic import BaseModel
from torch import Tensor

from neural.bounds import Bounds
from neural.rendering import SampleWeights

__all__ = ["RadianceModel", "RayBundleOutput", "Bounds"]


@dataclass
class RayBundleOutput:
    """A model's render of R rays.

    rgb (R,3), depth (R,), opacity (R,); aux_rgb: further predictions of the same pixels that the trainer
    also fits with an MSE term each (e.g. the vanilla model's coarse network); extra_loss: regularizers
    already weighted, added to the loss as they are; samples: the packed samples' weights (training renders
    of models that pack them; what the depth loss needs).
    """

    rgb: Tensor
    depth: Tensor
    opacity: Tensor
    aux_rgb: list[Tensor] = field(default_factory=list)
    extra_loss: Tensor | None = None
    samples: SampleWeights | None = None


class RadianceModel(torch.nn.Module):
    """A radiance field with its own sampler: renders rays given their bounds and a background colour.

    Subclasses set `model_name` (the name build_model knows them by) and `self.config` (a pydantic model
    whose `model_dump()` rebuilds them with build_model(model_name, scene, **config)).
    """

    model_name: ClassVar[str]
    #: Training settings this model works best with (keys of neural.config.MODEL_DEFAULTABLE), used
    #: where the user's TrainConfig leaves them unset.
    train_defaults: ClassVar[dict[str, Any]] = {}
    #: Whether the model renders `Bounds.unbounded` scenes (content beyond the scene box).
    supports_unbounded: ClassVar[bool] = False
    #: Whether training renders return their packed samples' weights (`RayBundleOutput.samples`).
    packs_samples: ClassVar[bool] = False
    config: BaseModel

    def __init__(self, scene: Bounds) -> None:
        super().__init__()
        self.scene = scene

    def render_rays(
        self,
        origins: Tensor,
        directions: Tensor,
        near: float,
        far: float,
        background: Tensor,
        train: bool,
        generator: torch.Generator | None = None,
    ) -> RayBundleOutput:
        """Render rays o + t d (unit d) for t in [near, far]; train=True jitters samples (using generator)."""
        raise NotImplementedError

    def on_train_step(self, step: int) -> bool:
        """Called by the trainer before the forward pass of each step (0-based global step), in train mode.

        Returns True when the model replaced its parameters (e.g. upsampled a grid): the trainer then
        rebuilds the optimizer from param_groups. Default: nothing to do.
        """
        return False

    def add_regularizer_gradients(self) -> None:
        """Called by the trainer after each step's backward pass: adds the gradients of the regularizers that
        the model forms directly (cheaper than through autograd) to its parameters' .grad. Default: none."""

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """Parameter groups with their learning rates for Adam; default: everything at lr."""
        return [{"params": list(self.parameters()), "lr": lr}]
