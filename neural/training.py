"""The training loop: random ray batches, Adam with exponential lr decay, logs, validation, checkpoints.

Orchestration only; the math lives in rays / sampling / rendering and the models.
"""

from __future__ import annotations

import json
import logging
import math
import random
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from estimation.artefacts import TRANSFORMS_NAME
from neural.appearance import PhotoAppearance
from neural.artefacts import IMAGE_CACHE_DIR, METRICS_FILE, RUN_CONFIG_FILE
from neural.budget import (
    PROBE_MAX_SIDE,
    PROBE_RENDER_RAYS,
    PROBE_STEPS,
    PROBE_WARMUP_STEPS,
    MeasuredRates,
    TrainSize,
    budget_steps,
    time_calls,
    train_max_side,
)
from neural.checkpoints import (
    list_checkpoints,
    load_checkpoint,
    load_model_state,
    resolve_checkpoint,
    save_checkpoint,
)
from neural.config import TrainConfig
from neural.data import FORMAT_DEFAULTS, Dataset, dataset_format, load_dataset_for
from neural.environment import ENVIRONMENT_RAYS, Environment, fit_environment
from neural.errors import CheckpointError
from neural.inference import (
    PinholeIntrinsics,
    background_colour,
    depth_to_uint8,
    orbit_parameters,
    read_run_config,
    render_background,
    render_image,
    render_rays_chunked,
    resolve_device,
    to_uint8,
)
from neural.models import RadianceModel, build_model, model_classes
from neural.rays import Rays, pixel_rays
from neural.rendering import packed_depth_loss

ProgressCallback = Callable[[str, float], None]
MetricsCallback = Callable[[dict[str, Any]], None]
StopReason = Literal["steps", "minutes", "stop_requested"]
#: Fewer depth rays in the training photos than this: too few points to supervise depth; trained without.
MIN_DEPTH_RAYS = 100

logger = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a call to train() did."""

    run_dir: Path
    step: int  # global steps done (including those before a resume)
    seconds: float  # wall-clock seconds of training in total
    final_loss: float
    final_psnr: float
    best_val_psnr: float | None
    latest_checkpoint: Path
    stopped_by: StopReason


def psnr_from_mse(mse: float) -> float:
    """PSNR = -10 log10(MSE) for images in [0,1]."""
    return -10.0 * math.log10(max(mse, 1e-10))


class RayBatchSampler:
    """Random training rays: uniform over all pixels of the training images, or over central crops."""

    def __init__(self, dataset: Dataset, indices: np.ndarray, device: torch.device) -> None:
        self.images = torch.as_tensor(dataset.images[indices], device=device)
        self.poses = torch.as_tensor(dataset.poses[indices], device=device)
        self.num_images, self.height, self.width = self.images.shape[:3]
        self.intrinsics = (dataset.fx, dataset.fy, dataset.cx, dataset.cy)
        self.device = device

    def sample(
        self, num_rays: int, generator: torch.Generator, crop_fraction: float | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """origins (R,3), directions (R,3), target colours (R,3) and training-image index (R,) of random
        pixels."""
        image = torch.randint(self.num_images, (num_rays,), generator=generator, device=self.device)
        if crop_fraction is None:
            u0, v0, crop_w, crop_h = 0, 0, self.width, self.height
        else:
            crop_w = max(1, round(self.width * crop_fraction))
            crop_h = max(1, round(self.height * crop_fraction))
            u0, v0 = (self.width - crop_w) // 2, (self.height - crop_h) // 2
        u = u0 + torch.randint(crop_w, (num_rays,), generator=generator, device=self.device)
        v = v0 + torch.randint(crop_h, (num_rays,), generator=generator, device=self.device)
        rays = pixel_rays(self.poses[image], u, v, *self.intrinsics)
        return rays.origins, rays.directions, self.images[image, v, u], image


class DepthRaySampler:
    """Random rays of the training photos with a known termination distance and its std-dev:
    sigma = sqrt(s^2 + depth_min_sigma^2), s each point's own (covariance) or their median (constant)."""

    def __init__(
        self, dataset: Dataset, indices: np.ndarray, config: TrainConfig, device: torch.device
    ) -> None:
        assert dataset.depth_rays is not None
        rays = dataset.depth_rays.of_images(indices)
        self.poses = torch.as_tensor(dataset.poses[indices], device=device)
        self.image = torch.as_tensor(rays.image, device=device)
        self.u = torch.as_tensor(rays.u, dtype=self.poses.dtype, device=device)
        self.v = torch.as_tensor(rays.v, dtype=self.poses.dtype, device=device)
        self.distance = torch.as_tensor(rays.distance, dtype=self.poses.dtype, device=device)
        self.median_sigma = float(np.median(rays.sigma)) if len(rays.sigma) else None
        own = rays.sigma
        if config.depth_uncertainty == "constant":
            own = np.full_like(rays.sigma, self.median_sigma or 0.0)
        sigma = np.sqrt(own**2 + config.depth_min_sigma**2)
        self.sigma = torch.as_tensor(sigma, dtype=self.poses.dtype, device=device)
        self.intrinsics = (dataset.fx, dataset.fy, dataset.cx, dataset.cy)

    def __len__(self) -> int:
        return int(self.image.shape[0])

    def sample(self, num_rays: int, generator: torch.Generator) -> tuple[Rays, Tensor, Tensor]:
        """Rays, their known distances and std-devs (R,) of random depth observations."""
        pick = torch.randint(len(self), (num_rays,), generator=generator, device=self.image.device)
        image = self.image[pick]
        rays = pixel_rays(self.poses[image], self.u[pick], self.v[pick], *self.intrinsics)
        return rays, self.distance[pick], self.sigma[pick]


def depth_sampler_for(
    dataset: Dataset, indices: np.ndarray, config: TrainConfig, model: RadianceModel, device: torch.device
) -> tuple[DepthRaySampler | None, dict[str, Any]]:
    """The depth rays a run trains with (None: without) and what config.json records about them."""
    if not config.depth_supervision:
        return None, {"used": False, "reason": "off"}
    reason = None
    if dataset.depth_rays is None:
        reason = f"{dataset.source} has no depths file"
    elif not model.packs_samples:
        reason = f"model {config.model!r} does not render the per-sample weights the depth loss needs"
    sampler = None if reason else DepthRaySampler(dataset, indices, config, device)
    if sampler is not None and len(sampler) < MIN_DEPTH_RAYS:
        reason = f"too few sparse points: {len(sampler)} depth rays in training photos (< {MIN_DEPTH_RAYS})"
    if reason:
        logger.warning("training without depth supervision: %s", reason)
        return None, {"used": False, "reason": reason}
    assert sampler is not None
    record = {"used": True, "rays": len(sampler), "median_sigma": sampler.median_sigma,
              "uncertainty": config.depth_uncertainty}  # fmt: skip
    logger.info("depth supervision on %d rays (median sigma %.4g)", len(sampler), sampler.median_sigma)
    return sampler, record


def downscale(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean of factor x factor pixel blocks (the image cropped to whole blocks); (H//f, W//f, 3)."""
    if factor == 1:
        return image
    height, width = image.shape[0] // factor, image.shape[1] // factor
    blocks = image[: height * factor, : width * factor].reshape(height, factor, width, factor, -1)
    return blocks.mean(axis=(1, 3))


def learning_rate_factor(step: int, config: TrainConfig) -> float:
    """lr(step) / lr(0) = lr_decay ^ (step / lr_decay_steps)."""
    return config.lr_decay ** (step / config.lr_decay_steps)


def build_optimizer(
    model: RadianceModel, config: TrainConfig, appearance: PhotoAppearance | None = None
) -> torch.optim.Adam:
    groups = model.param_groups(config.lr)
    if appearance is not None:
        groups.append({"params": list(appearance.parameters()), "lr": config.photo_appearance_lr,
                       "name": "appearance"})  # fmt: skip
    for group in groups:
        group["initial_lr"] = group["lr"]
    # The fused kernel: one pass over each parameter instead of a dozen (6x faster on a 2-core CPU for the
    # fast model's 10M-value grids); it needs float32 tensors on one CPU or CUDA device.
    params = [p for group in groups for p in group["params"]]
    fused = all(p.dtype == torch.float32 and p.device.type in ("cpu", "cuda") for p in params)
    return torch.optim.Adam(groups, fused=fused)


def set_learning_rate(optimizer: torch.optim.Optimizer, factor: float) -> float:
    for group in optimizer.param_groups:
        group["lr"] = group["initial_lr"] * factor
    return optimizer.param_groups[0]["lr"]


def rng_states(generator: torch.Generator) -> dict[str, Any]:
    states = {
        "generator": generator.get_state(),
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def restore_rng_states(states: dict[str, Any], generator: torch.Generator) -> None:
    """The random states of a checkpoint. A run resumed on another kind of device (a GPU run on a CPU) cannot
    continue its ray draws' sequence, whose state has another form there: the generator is seeded from it."""
    saved = states["generator"].cpu()
    if saved.numel() == generator.get_state().numel():
        generator.set_state(saved)
    else:
        generator.manual_seed(int.from_bytes(bytes(saved[:8].tolist()), "little"))
    torch.set_rng_state(states["torch"].cpu())
    np.random.set_state(states["numpy"])
    random.setstate(states["python"])
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([state.cpu() for state in states["cuda"]])


def run_config_for(config: TrainConfig, dataset: Dataset, data: Path) -> dict[str, Any]:
    """config.json: the resolved training config and what rendering the run needs about its data."""
    train_poses = dataset.poses[dataset.split("train")].astype(np.float64)
    return {
        "train": config.model_dump(mode="json"),
        "data": str(data),
        "scene": dataset.scene.to_dict(),
        "normalization": dataset.normalization.to_dict(),
        "camera": {
            "width": dataset.width,
            "height": dataset.height,
            "fx": dataset.fx,
            "fy": dataset.fy,
            "cx": dataset.cx,
            "cy": dataset.cy,
        },
        "orbit": orbit_parameters(train_poses),
        # every registered camera (held-out ones too), scene frame: the default view and video path
        "cameras": {
            "c2w": dataset.poses.astype(np.float64).tolist(),
            "photos": dataset_format(data) == "reconstruction",
            "held_out": [int(index) for index in dataset.split("val")],
        },
    }


def resume_config(run_dir: Path, overrides: TrainConfig | None) -> TrainConfig:
    """The stored config; of `overrides`, only explicitly set steps/minutes/device/val/checkpoint cadence."""
    stored = TrainConfig.model_validate(read_run_config(run_dir)["train"])
    if overrides is None:
        return stored
    if "model" in overrides.model_fields_set and overrides.model != stored.model:
        raise CheckpointError(
            f"{run_dir}: the run trains model {stored.model!r}; cannot resume it as {overrides.model!r}"
        )
    allowed = ("steps", "minutes", "device", "val_every", "checkpoint_every", "log_every", "chunk_rays")
    update = {name: getattr(overrides, name) for name in allowed if name in overrides.model_fields_set}
    if "steps" in update:
        update.setdefault("minutes", None)
    if "minutes" in update:
        update.setdefault("steps", None)
    return TrainConfig.model_validate({**stored.model_dump(), **update})


def check_same_data(stored: dict[str, Any], current: dict[str, Any], run_dir: Path) -> None:
    """Resuming needs the data the run started on: same scene bounds, normalization and camera."""
    for key in ("scene", "normalization", "camera"):
        if json.loads(json.dumps(current[key])) != stored[key]:
            raise CheckpointError(
                f"{run_dir}: the data's {key} differs from the run's ({RUN_CONFIG_FILE}); resume with the "
                f"data it was trained on ({stored['data']})"
            )


class Trainer:
    """One training run in run_dir; construct, then call run()."""

    def __init__(
        self,
        data: Path,
        run_dir: Path,
        config: TrainConfig,
        resume: bool,
        progress: ProgressCallback | None,
        metrics_callback: MetricsCallback | None,
        should_stop: Callable[[], bool] | None,
        train_size: TrainSize | None = None,
    ) -> None:
        self.run_dir = run_dir
        self.progress = progress
        self.metrics_callback = metrics_callback
        self.should_stop = should_stop
        model_type, _ = model_classes(config.model)
        self.config = config.resolved(model_type.train_defaults).for_data(
            FORMAT_DEFAULTS[dataset_format(data)], model_type.supports_unbounded
        )
        self.dataset = load_dataset_for(data, self.config, run_dir / IMAGE_CACHE_DIR)
        self.device = resolve_device(self.config.device)
        self.background = background_colour(self.config.background, self.device)
        self.sampler = RayBatchSampler(self.dataset, self.dataset.split("train"), self.device)
        self.environment = self._fit_environment() if self.config.background == "random" else None
        self.render_background = render_background(self.config, self.environment, self.device)
        self.val_index = self._first_val_index()
        camera = PinholeIntrinsics(
            self.dataset.width, self.dataset.height, self.dataset.fx, self.dataset.fy, self.dataset.cx,
            self.dataset.cy,
        )  # fmt: skip
        self.val_factor = math.ceil(max(camera.width, camera.height) / self.config.val_max_side)
        self.val_camera = camera.downscaled(self.val_factor)

        torch.manual_seed(self.config.seed)  # the model's initial weights
        self.model = build_model(self.config.model, self.dataset.scene, **self.config.model_options).to(
            self.device
        )
        self.appearance = None
        if self.config.photo_appearance:
            self.appearance = PhotoAppearance(len(self.dataset.split("train"))).to(self.device)
        self.generator = torch.Generator(device=self.device).manual_seed(self.config.seed)
        self.step, self.elapsed_before, self.best_val_psnr, self.last_val_psnr = 0, 0.0, None, None
        if resume:
            self._restore()
        else:
            self.optimizer = build_optimizer(self.model, self.config, self.appearance)
        self.depth_sampler, depth_record = depth_sampler_for(
            self.dataset, self.dataset.split("train"), self.config, self.model, self.device
        )
        run_config = run_config_for(self.config, self.dataset, Path(data).resolve())
        run_config["depth_supervision"] = depth_record
        if resume:
            stored = read_run_config(run_dir)
            check_same_data(stored, run_config, run_dir)
            train_size = train_size or stored.get("train_size")
        if train_size is not None:
            run_config["train_size"] = train_size if isinstance(train_size, dict) else train_size.to_dict()
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / RUN_CONFIG_FILE).write_text(json.dumps(run_config, indent=2))

    def _first_val_index(self) -> int | None:
        for split in ("val", "test"):
            indices = self.dataset.splits.get(split)
            if indices is not None and len(indices):
                return int(indices[0])
        return None

    def _restore(self) -> None:
        path = resolve_checkpoint(self.run_dir, "latest")
        payload = load_checkpoint(path, map_location=self.device)
        if payload.get("model_name") != self.config.model:
            raise CheckpointError(
                f"{path}: checkpoint holds model {payload.get('model_name')!r}, not {self.config.model!r}"
            )
        # The model as it was saved (its full config), not as today's defaults would build it.
        self.model = build_model(self.config.model, self.dataset.scene, **payload["model_config"]).to(
            self.device
        )
        load_model_state(self.model, payload["model_state"], path)
        if self.appearance is not None:
            self.appearance.load_state_dict(payload["appearance_state"])
        self.optimizer = build_optimizer(self.model, self.config, self.appearance)
        try:
            self.optimizer.load_state_dict(payload["optimizer_state"])
        except (ValueError, KeyError) as error:
            raise CheckpointError(f"{path}: optimizer state does not fit the model ({error})") from None
        restore_rng_states(payload["rng"], self.generator)
        self.step = int(payload["step"])
        self.elapsed_before = float(payload["elapsed_seconds"])
        self.best_val_psnr = payload.get("best_val_psnr")

    def _fit_environment(self) -> Environment:
        """The training photos' colours by direction (neural.environment), from ENVIRONMENT_RAYS random
        pixels drawn by a generator of their own (the training's random sequence stays as it was)."""
        generator = torch.Generator(device=self.device).manual_seed(self.config.seed)
        _, directions, colours, _ = self.sampler.sample(ENVIRONMENT_RAYS, generator)
        return fit_environment(directions, colours)

    def measure_rates(self) -> MeasuredRates:
        """Seconds per training step and per rendered ray, timed here (the steps train this model)."""
        seconds_per_step = time_calls(self._train_step, PROBE_WARMUP_STEPS, PROBE_STEPS)
        return MeasuredRates(seconds_per_step, self.seconds_per_ray())

    def seconds_per_ray(self) -> float:
        """Seconds per rendered ray (no gradients) of the model as it is now, timed on training rays."""
        generator = torch.Generator(device=self.device).manual_seed(self.config.seed)
        origins, directions, _, _ = self.sampler.sample(PROBE_RENDER_RAYS, generator)
        scene, background, chunk = self.dataset.scene, self.render_background, self.config.chunk_rays
        seconds = time_calls(
            lambda: render_rays_chunked(self.model, origins, directions, scene, background, chunk), 0, 1
        )
        return seconds / PROBE_RENDER_RAYS

    def record_render_rate(self) -> None:
        """config.json's train_size takes the trained model's render rate (a filled field renders slower
        than the probe's empty one), which the views stage plans with."""
        path = self.run_dir / RUN_CONFIG_FILE
        info = json.loads(path.read_text())
        if "train_size" in info:
            info["train_size"]["render_seconds_per_ray"] = self.seconds_per_ray()
            path.write_text(json.dumps(info, indent=2))

    # ------------------------------------------------------------------------------------------------
    def run(self) -> TrainResult:
        config = self.config
        start = time.perf_counter()
        loss_value, psnr_value = float("nan"), float("nan")
        stopped_by: StopReason | None = self._stop_reason(self.elapsed_before)
        latest = None
        if stopped_by and not list_checkpoints(self.run_dir):  # stopped before the first step
            latest = self._save(self.elapsed_before)
        metrics_file = (self.run_dir / METRICS_FILE).open("a")
        try:
            while stopped_by is None:
                loss_value, psnr_value, lr = self.train_step()
                seconds = self.elapsed_before + time.perf_counter() - start
                stopped_by = self._stop_reason(seconds)
                if self.step % config.log_every == 0 or stopped_by:
                    record = {
                        "step": self.step,
                        "loss": loss_value,
                        "psnr": psnr_value,
                        "lr": lr,
                        "seconds": seconds,
                    }
                    self._emit(metrics_file, record)
                if self.val_index is not None and (
                    self.step % config.val_every == 0
                    or self.step % config.checkpoint_every == 0
                    or stopped_by
                ):
                    self._emit(
                        metrics_file, {"step": self.step, "val_psnr": self._validate(), "seconds": seconds}
                    )
                if self.step % config.checkpoint_every == 0 or stopped_by:
                    latest = self._save(self.elapsed_before + time.perf_counter() - start)
                if self.progress is not None:
                    self.progress("train", self._fraction(seconds))
        finally:
            metrics_file.close()
        return TrainResult(
            run_dir=self.run_dir,
            step=self.step,
            seconds=self.elapsed_before + time.perf_counter() - start,
            final_loss=loss_value,
            final_psnr=psnr_value,
            best_val_psnr=self.best_val_psnr,
            latest_checkpoint=latest or resolve_checkpoint(self.run_dir, "latest"),
            stopped_by=stopped_by,
        )

    def train_step(self) -> tuple[float, float, float]:
        """One optimisation step (the step count advances); its loss (without the regularizers the model adds
        as gradients), PSNR and learning rate."""
        result = self._train_step()
        self.step += 1
        return result

    def _train_step(self) -> tuple[float, float, float]:
        config = self.config
        self.model.train()
        if self.model.on_train_step(self.step):
            # The model replaced its parameters (e.g. upsampled grids): Adam starts afresh for them.
            self.optimizer = build_optimizer(self.model, config, self.appearance)
        lr = set_learning_rate(self.optimizer, learning_rate_factor(self.step, config))
        crop = config.precrop_fraction if self.step < config.precrop_steps else None
        origins, directions, target, photo = self.sampler.sample(config.batch_rays, self.generator, crop)
        num_colour = origins.shape[0]
        if self.depth_sampler is not None:  # rendered in the same pass, after the colour rays
            depth_rays, depth, sigma = self.depth_sampler.sample(config.depth_rays, self.generator)
            origins = torch.cat([origins, depth_rays.origins.to(origins.dtype)])
            directions = torch.cat([directions, depth_rays.directions.to(directions.dtype)])
        background = self.background
        if config.background == "random":  # nothing may show through: the scene must be opaque
            background = torch.rand(
                (origins.shape[0], 3), generator=self.generator, device=self.device
            )
        out = self.model.render_rays(
            origins, directions, self.dataset.near, self.dataset.far, background, train=True,
            generator=self.generator,
        )  # fmt: skip
        rgb, aux_rgb = out.rgb[:num_colour], [aux[:num_colour] for aux in out.aux_rgb]
        if self.appearance is not None:
            rgb, aux_rgb = self.appearance(rgb, photo), [self.appearance(aux, photo) for aux in aux_rgb]
        mse = torch.mean((rgb - target) ** 2)
        loss = mse + sum((torch.mean((aux - target) ** 2) for aux in aux_rgb), torch.zeros_like(mse))
        if self.appearance is not None:
            loss = loss + config.photo_appearance_weight * self.appearance.penalty()
        if out.extra_loss is not None:
            loss = loss + out.extra_loss
        if self.depth_sampler is not None:
            assert out.samples is not None
            loss = loss + config.depth_weight * packed_depth_loss(
                out.samples, num_colour, depth.to(mse.dtype), sigma.to(mse.dtype)
            )
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.model.add_regularizer_gradients()
        self.optimizer.step()
        return loss.item(), psnr_from_mse(mse.item()), lr

    def _stop_reason(self, seconds: float) -> StopReason | None:
        if self.config.steps is not None and self.step >= self.config.steps:
            return "steps"
        if self.config.minutes is not None and seconds >= 60.0 * self.config.minutes:
            return "minutes"
        if self.should_stop is not None and self.should_stop():
            return "stop_requested"
        return None

    def _fraction(self, seconds: float) -> float:
        if self.config.steps is not None:
            return min(1.0, self.step / self.config.steps)
        return min(1.0, seconds / (60.0 * self.config.minutes))

    def _emit(self, metrics_file: Any, record: dict[str, Any]) -> None:
        metrics_file.write(json.dumps(record) + "\n")
        metrics_file.flush()
        if self.metrics_callback is not None:
            self.metrics_callback(record)

    def _validate(self) -> float:
        """Render the first validation view, save ground truth | render | depth as val/step_N.png; PSNR."""
        pose = torch.as_tensor(self.dataset.poses[self.val_index], device=self.device)
        rendered = render_image(
            self.model, pose, self.val_camera, self.dataset.scene, self.render_background,
            self.config.chunk_rays,
        )
        truth = torch.as_tensor(
            downscale(self.dataset.images[self.val_index], self.val_factor), device=self.device
        )
        val_psnr = psnr_from_mse(float(torch.mean((rendered.rgb - truth) ** 2)))
        panel = np.concatenate(
            [to_uint8(truth), to_uint8(rendered.rgb), depth_to_uint8(rendered.depth, self.dataset.scene)],
            axis=1,
        )
        (self.run_dir / "val").mkdir(exist_ok=True)
        Image.fromarray(panel).save(self.run_dir / "val" / f"step_{self.step:07d}.png")
        self.last_val_psnr = val_psnr
        if self.best_val_psnr is None or val_psnr > self.best_val_psnr:
            self.best_val_psnr = val_psnr
        return val_psnr

    def _save(self, elapsed: float) -> Path:
        payload = {
            "model_name": self.config.model,
            "model_config": self.model.config.model_dump(mode="json"),
            "model_state": self.model.state_dict(),
            **({} if self.appearance is None else {"appearance_state": self.appearance.state_dict()}),
            **({} if self.environment is None else {"environment": self.environment.to_list()}),
            "optimizer_state": self.optimizer.state_dict(),
            "train_config": self.config.model_dump(mode="json"),
            "scene": self.dataset.scene.to_dict(),
            "rng": rng_states(self.generator),
            "elapsed_seconds": elapsed,
            "best_val_psnr": self.best_val_psnr,
        }
        return save_checkpoint(self.run_dir, payload, self.step, self.last_val_psnr)


def size_for_budget(data: Path, config: TrainConfig) -> tuple[TrainConfig, TrainSize | None]:
    """Photos given no size (max_side, downscale) train at the long side that their budget can train
    (neural.budget.train_max_side), from the step time a short probe measures; other data as it is."""
    if (
        config.max_side is not None
        or config.downscale is not None
        or dataset_format(data) != "reconstruction"
    ):
        return config, None
    with tempfile.TemporaryDirectory() as folder:
        probe = Trainer(
            data,
            Path(folder),
            config.model_copy(update={"max_side": PROBE_MAX_SIDE}),
            False,
            None,
            None,
            None,
        )
        rates = probe.measure_rates()
    meta = json.loads((data / TRANSFORMS_NAME).read_text())
    width, height = int(meta["w"]), int(meta["h"])
    steps = budget_steps(probe.config.steps, probe.config.minutes, rates.seconds_per_step)
    train_images = len(probe.dataset.split("train"))
    side = train_max_side(steps, probe.config.batch_rays, train_images, width, height)
    size = TrainSize(side, max(width, height), steps, rates.seconds_per_step, rates.render_seconds_per_ray)
    return config.model_copy(update={"max_side": side}), size


def train(
    data: Path | str,
    run_dir: Path | str,
    config: TrainConfig | None = None,
    resume: bool = False,
    progress: ProgressCallback | None = None,
    metrics_callback: MetricsCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> TrainResult:
    """Train a radiance field on `data` into run_dir (config.json, metrics.jsonl, val/, checkpoints/).

    resume=True continues from the latest checkpoint with the stored config (config may then only change
    steps/minutes/device and the logging cadence); the next steps equal those of an uninterrupted run.
    """
    run_dir = Path(run_dir)
    if resume:
        config = resume_config(run_dir, config)
    else:
        if list_checkpoints(run_dir):
            raise CheckpointError(
                f"{run_dir}: already holds a training run; resume it or choose another folder"
            )
        config = config or TrainConfig()
    train_size = None
    if not resume:
        config, train_size = size_for_budget(Path(data), config)
    trainer = Trainer(
        Path(data), run_dir, config, resume, progress, metrics_callback, should_stop, train_size
    )
    result = trainer.run()
    trainer.record_render_rate()
    return result
