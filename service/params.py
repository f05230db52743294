"""Typed parameters of each job kind, stored as the job's `params` (validated on the way in and out).

The nested configurations (`estimation.ReconstructionConfig`, `neural.TrainConfig`) are validated by
their own models where the heavy packages are loaded: the actions that create jobs and the job functions.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from service.kinds import JobKind, require_every_kind


class ReconstructionParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    config: dict[str, Any] = Field(
        default_factory=dict, description="estimation.ReconstructionConfig as JSON (defaults when empty)."
    )


class NerfParams(BaseModel):
    model_config = ConfigDict(extra="forbid")

    train_config: dict[str, Any] = Field(default_factory=dict, description="neural.TrainConfig as JSON.")
    dataset: str | None = Field(
        None, description="The uploaded dataset, relative to the job folder; None: the source reconstruction."
    )


class VideoParams(BaseModel):
    """A video of a NeRF job's latest checkpoint; frames x width x height is capped by a budget."""

    model_config = ConfigDict(extra="forbid")

    num_frames: int = Field(36, ge=1, le=720, examples=[36])
    width: int = Field(200, ge=8, le=4096, examples=[200])
    height: int = Field(200, ge=8, le=4096, examples=[200])
    path: Literal["captured", "orbit"] = Field(
        "captured",
        description="captured: a smooth path through a photo scene's registered cameras (round them only "
        "when they close a ring; Blender and .npz data orbit); orbit: a circle round the scene (free mode).",
    )

    @property
    def pixels(self) -> int:
        return self.num_frames * self.width * self.height


class EvaluationParams(BaseModel):
    """Held-out renders of a NeRF job's latest checkpoint against its data (a scene's last stage)."""

    model_config = ConfigDict(extra="forbid")

    split: Literal["train", "val", "test"] = Field("val", description="The dataset split rendered.")
    max_side: int = Field(
        200, ge=8, le=4096, description="The views are rendered downscaled to at most this long side."
    )


JobParams = ReconstructionParams | NerfParams | VideoParams | EvaluationParams
PARAMS_OF_KIND: dict[JobKind, type[BaseModel]] = {
    JobKind.reconstruction: ReconstructionParams,
    JobKind.nerf: NerfParams,
    JobKind.video: VideoParams,
    JobKind.evaluation: EvaluationParams,
}
require_every_kind(PARAMS_OF_KIND, "job parameters")


def parse_params(kind: str, params: dict[str, Any] | BaseModel) -> Any:
    """The typed parameters of a job of `kind` (ValidationError when they do not fit)."""
    model = PARAMS_OF_KIND[kind]
    return params if isinstance(params, model) else model.model_validate(params)
