"""Image quality of a trained run on a dataset split: PSNR and SSIM per image and their means."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from neural.artefacts import IMAGE_CACHE_DIR
from neural.data import Dataset, load_dataset_for
from neural.inference import LoadedRun, PinholeIntrinsics, load_run, render_frame, to_uint8


@dataclass(frozen=True)
class ImageMetrics:
    name: str
    psnr: float
    ssim: float


@dataclass(frozen=True)
class EvalResult:
    """Per-image and mean PSNR (dB) and SSIM of a run's renders against a split's images."""

    split: str
    step: int
    per_image: list[ImageMetrics]
    mean_psnr: float
    mean_ssim: float
    seconds_per_image: float

    def to_dict(self) -> dict:
        return asdict(self)


def psnr(rendered: np.ndarray, truth: np.ndarray) -> float:
    """PSNR = -10 log10(mean (rendered - truth)^2), images float in [0,1]."""
    mse = float(np.mean((np.asarray(rendered, np.float64) - np.asarray(truth, np.float64)) ** 2))
    return -10.0 * math.log10(max(mse, 1e-12))


def ssim(rendered: np.ndarray, truth: np.ndarray) -> float:
    """Structural similarity (skimage, Gaussian-weighted as in the NeRF papers) of two RGB images in [0,1]."""
    from skimage.metrics import structural_similarity

    return float(
        structural_similarity(
            np.asarray(rendered, np.float64),
            np.asarray(truth, np.float64),
            channel_axis=-1,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    )


def evaluate(
    run_dir: Path | str,
    data: Path | str | Dataset,
    split: str = "val",
    checkpoint: str = "latest",
    out_dir: Path | str | None = None,
    device: str = "auto",
) -> EvalResult:
    """Render every view of `split` of `data` with the run and compare; optionally save renders to out_dir.

    A data path is loaded as the run trained on it (its background and image size, so the views are
    rendered and compared at the training size).
    """
    run = load_run(run_dir, checkpoint, device=device)
    dataset = (
        data
        if isinstance(data, Dataset)
        else load_dataset_for(data, run.config, Path(run_dir) / IMAGE_CACHE_DIR)
    )
    return evaluate_run(run, dataset, split, out_dir)


def evaluate_run(
    run: LoadedRun, dataset: Dataset, split: str = "val", out_dir: Path | str | None = None
) -> EvalResult:
    """Render every view of `split` of `dataset` with a loaded run and compare (see `evaluate`)."""
    import time

    camera = PinholeIntrinsics(dataset.width, dataset.height, dataset.fx, dataset.fy, dataset.cx, dataset.cy)
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    metrics, seconds = [], 0.0
    for index in dataset.split(split):
        start = time.perf_counter()
        c2w_original = dataset.normalization.pose_to_original(dataset.poses[index])
        with torch.no_grad():
            rendered = render_frame(run, c2w_original, camera).rgb.cpu().numpy()
        seconds += time.perf_counter() - start
        truth = dataset.images[index]
        name = Path(dataset.image_names[index]).stem
        metrics.append(ImageMetrics(name=name, psnr=psnr(rendered, truth), ssim=ssim(rendered, truth)))
        if out_dir is not None:
            from PIL import Image

            Image.fromarray(to_uint8(rendered)).save(Path(out_dir) / f"{name}.png")
    return EvalResult(
        split=split,
        step=run.step,
        per_image=metrics,
        mean_psnr=float(np.mean([m.psnr for m in metrics])),
        mean_ssim=float(np.mean([m.ssim for m in metrics])),
        seconds_per_image=seconds / len(metrics),
    )


def write_eval_json(result: EvalResult, path: Path) -> None:
    path.write_text(json.dumps(result.to_dict(), indent=2))
