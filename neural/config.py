"""Typed training configuration shared by the CLI, the REST service and the tests."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: The radiance models by name (neural.models.MODEL_REGISTRY holds their classes); kept here, free of torch,
#: so that the CLI and the API can offer them without importing torch.
ModelName = Literal["vanilla", "fast", "tensorf"]

#: Settings a model may choose itself (its class attribute `train_defaults`) when the user leaves them unset.
MODEL_DEFAULTABLE = ("steps", "batch_rays", "lr", "lr_decay", "lr_decay_steps", "precrop_steps")
#: Fallbacks when neither the user nor the model sets them.
GENERIC_DEFAULTS: dict[str, Any] = {
    "steps": 2000,
    "batch_rays": 4096,
    "lr": 5e-4,
    "lr_decay": 0.1,
    "lr_decay_steps": 250_000,
    "precrop_steps": 0,
}


class TrainConfig(BaseModel):
    """How to train a radiance field. Fields left at None take the model's defaults (see `resolved`)."""

    model_config = ConfigDict(extra="forbid")

    model: ModelName = Field("fast", description="Which radiance model to train.")
    model_options: dict[str, Any] = Field(
        default_factory=dict, description="Overrides of the model's own config (build_model keywords)."
    )
    steps: int | None = Field(None, ge=1, description="Stop after this many optimisation steps.")
    minutes: float | None = Field(None, gt=0, description="Stop after this much training wall-clock time.")
    batch_rays: int | None = Field(None, ge=1, description="Random rays per optimisation step.")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="auto: cuda when available.")
    seed: int = Field(0, description="Seeds ray selection, sample jitter and the model's initial weights.")
    lr: float | None = Field(
        None, gt=0, description="Adam learning rate at step 0 (models may set per group)."
    )
    lr_decay: float | None = Field(None, gt=0, le=1, description="lr(step) = lr * lr_decay^(step / steps).")
    lr_decay_steps: int | None = Field(None, ge=1, description="The steps over which lr falls by lr_decay.")
    precrop_steps: int | None = Field(
        None, ge=0, description="Sample rays from the central crop of each image for this many first steps."
    )
    precrop_fraction: float = Field(0.5, gt=0, le=1, description="Side of the central crop / image side.")
    checkpoint_every: int = Field(500, ge=1, description="Save a checkpoint every this many steps.")
    val_every: int = Field(500, ge=1, description="Render a validation view (PNG, PSNR) this often.")
    val_max_side: int = Field(
        400, ge=8, description="Validation renders are downscaled by a whole factor to at most this side."
    )
    log_every: int = Field(10, ge=1, description="Write a metrics.jsonl line every this many steps.")
    chunk_rays: int = Field(
        8192, ge=1, description="Rays rendered at once outside training; lower it if you run out of memory."
    )
    background: Literal["white", "black", "random"] | None = Field(
        None,
        description="Colour behind the scene: white or black (RGBA data composited on it, renders on it), or "
        "random (a random colour per training ray, so the scene must be opaque; renders on the photos' "
        "environment, see render_environment). "
        "None: the data's default (white for Blender/npz, random for photographs).",
    )
    render_environment: bool = Field(
        True,
        description="Renders of a run trained on random colours (photographs) show, where the field is "
        "empty, the training photos' colours by direction (a first-degree fit, neural.environment); "
        "false: black.",
    )
    unbounded: bool | None = Field(
        None,
        description="Content beyond the scene box, out to far away (contracted space; fast model). "
        "None: the data's default (true for `sfmnerf reconstruct` output, false for Blender/npz).",
    )
    max_side: int | None = Field(
        None, ge=8, description="Train on the images shrunk to at most this many pixels on their longer side."
    )
    downscale: float | None = Field(None, ge=1, description="Train on the images shrunk by this factor.")
    photo_appearance: bool = Field(
        False,
        description="Learn an affine colour transform per training photo (exposure, white balance); "
        "novel views and held-out photos are rendered with the photos' mean, the identity.",
    )
    photo_appearance_weight: float = Field(
        0.1, ge=0, description="Weight of the transforms' squared distance from the identity."
    )
    photo_appearance_lr: float = Field(1e-3, gt=0, description="Adam learning rate of the transforms.")
    depth_supervision: bool | None = Field(
        None,
        description="Add the ray-termination (depth) loss on the rays through the reconstruction's sparse "
        "points (its depths.npz). None: the data's default (true for `sfmnerf reconstruct` output, false for "
        "Blender/npz). Without enough points the run trains without it and says so in config.json.",
    )
    depth_weight: float = Field(0.01, ge=0, description="Weight of the depth loss beside the colour MSE.")
    depth_uncertainty: Literal["covariance", "constant"] = Field(
        "covariance",
        description="Each point's std-dev along its ray from the bundle adjustment's covariance, or one "
        "std-dev (their median) for every point.",
    )
    depth_rays: int = Field(512, ge=1, description="Rays with a known depth rendered per step.")
    depth_min_sigma: float = Field(
        0.04,
        gt=0,
        description="Added in quadrature to each depth's std-dev, in scene units (the scene box spans "
        "[-1, 1]): how far a ray's termination may spread about its point (0.04: about 4 voxels of "
        "fountain-P11's final grid). 0.04 instead of 0.01 gained 0.37-0.40 dB on fountain-P11's held-out "
        "photos in 10 minutes at 800 px (0.08: 0.17).",
    )

    @model_validator(mode="before")
    @classmethod
    def _legacy_white_background(cls, data: Any) -> Any:
        """Runs written before `background` existed stored white_background: true/false."""
        if isinstance(data, dict) and "white_background" in data:
            data = dict(data)
            white = data.pop("white_background")
            data.setdefault("background", "white" if white else "black")
        return data

    @model_validator(mode="after")
    def _steps_or_minutes(self) -> TrainConfig:
        if self.steps is not None and self.minutes is not None:
            raise ValueError("give steps or minutes, not both")
        return self

    @property
    def white_background(self) -> bool:
        """RGBA images are composited on white (else black)."""
        return self.background in (None, "white")

    def for_data(self, data_defaults: dict[str, Any], model_supports_unbounded: bool) -> TrainConfig:
        """A copy with background / unbounded / depth_supervision filled from the data format's defaults
        where unset, and its model options for this model under the user's.

        An unbounded scene is the default only for models that render one; asking for it explicitly with
        another model is an error.
        """
        filled = {
            name: data_defaults[name]
            for name in ("background", "unbounded", "depth_supervision")
            if getattr(self, name) is None
        }
        model_defaults = data_defaults.get("model_options", {}).get(self.model, {})
        if model_defaults:
            filled["model_options"] = {**model_defaults, **self.model_options}
        if "unbounded" in filled:
            filled["unbounded"] = filled["unbounded"] and model_supports_unbounded
        elif self.unbounded and not model_supports_unbounded:
            raise ValueError(f"model {self.model!r} does not support unbounded scenes (unbounded: true)")
        return self.model_copy(update=filled)

    def resolved(self, model_defaults: dict[str, Any]) -> TrainConfig:
        """A copy with every None setting filled from the model's defaults, then the generic ones."""
        filled = {}
        for name in MODEL_DEFAULTABLE:
            if getattr(self, name) is None:
                if name == "steps" and self.minutes is not None:
                    continue
                filled[name] = model_defaults.get(name, GENERIC_DEFAULTS[name])
        return self.model_copy(update=filled)
