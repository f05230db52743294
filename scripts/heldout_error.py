"""Where a photo run's held-out error lies (benchmarks/RESULTS.md, bench_nerf_real): for each held-out photo,
its PSNR and the share of its squared error in the pixels whose ray direction no training photo's view
contains (content at a distance there was never photographed), the render's mean colour minus the photo's
and the PSNR without it, and the share of its squared error and the PSNR in bands of columns (split at the
fractions of the width --column-splits gives: content at a photo's sides may be in no other photo); and the
PSNR on random pixels of each training photo, with the same bias.

    python3 scripts/heldout_error.py RUN_DIR RECONSTRUCTION_DIR [--pixels 8192] [--column-splits 0.25,0.9]

RUN_DIR is a trained run (bench_nerf_real's OUT/SCENE/CONFIG), RECONSTRUCTION_DIR the reconstruction it was
trained on (OUT/sfm/SCENE). Directions are compared in the run's scene frame with each training camera's
pinhole view (OpenGL axes: the camera looks down -z, image y up).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from neural.artefacts import IMAGE_CACHE_DIR
from neural.data import load_dataset_for
from neural.inference import PinholeIntrinsics, load_run, render_frame, render_rays_chunked
from neural.rays import generate_rays


def unseen_directions(directions: np.ndarray, dataset, training: np.ndarray) -> np.ndarray:
    """(N,) True where no training camera's view contains the unit direction (directions (N, 3), scene
    frame): u = fx x / (-z) + cx, v = -fy y / (-z) + cy in the camera's axes, inside [0, W) x [0, H)."""
    seen = np.zeros(len(directions), bool)
    for index in training:
        camera = directions @ dataset.poses[index][:3, :3]        # world -> camera axes: R^T d
        depth = -camera[:, 2]
        ahead = depth > 1e-9
        u = dataset.fx * camera[:, 0] / np.where(ahead, depth, 1.0) + dataset.cx
        v = -dataset.fy * camera[:, 1] / np.where(ahead, depth, 1.0) + dataset.cy
        seen |= ahead & (u >= 0) & (u < dataset.width) & (v >= 0) & (v < dataset.height)
    return ~seen


def rays_of(dataset, index: int):
    """The rays of every pixel of the dataset's photo `index` (scene frame)."""
    pose = torch.as_tensor(dataset.poses[index], dtype=torch.float32)
    return generate_rays(pose, dataset.width, dataset.height, dataset.fx, dataset.fy, dataset.cx, dataset.cy)


def psnr(squared_error: float) -> float:
    return float(-10.0 * np.log10(squared_error))


def column_bands(error: np.ndarray, splits: list[float]) -> str:
    """Each band of columns of the (H, W) squared error, split at the width fractions `splits`: its share
    of the squared error and its PSNR."""
    width = error.shape[1]
    edges = [0, *(round(fraction * width) for fraction in splits), width]
    return "; ".join(
        f"columns {low}-{high}: {error[:, low:high].sum() / error.sum():.1%} of it, "
        f"PSNR {psnr(error[:, low:high].mean()):.2f} dB"
        for low, high in zip(edges[:-1], edges[1:], strict=True)
    )


def width_fractions(text: str) -> list[float]:
    """--column-splits: increasing fractions of the width strictly between 0 and 1, comma-separated."""
    try:
        fractions = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of numbers") from None
    if any(not 0 < f < 1 for f in fractions) or fractions != sorted(set(fractions)):
        raise argparse.ArgumentTypeError(f"{text!r}: the fractions must increase, strictly between 0 and 1")
    return fractions


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("reconstruction", type=Path)
    parser.add_argument("--pixels", type=int, default=8192, help="random pixels rendered per training photo")
    parser.add_argument("--column-splits", type=width_fractions, default=[0.25, 0.9],
                        help="width fractions where the held-out photos' column bands split (0.25,0.9)")
    args = parser.parse_args()

    run = load_run(args.run_dir, device="cpu")
    dataset = load_dataset_for(args.reconstruction, run.config, args.run_dir / IMAGE_CACHE_DIR)
    camera = PinholeIntrinsics(dataset.width, dataset.height, dataset.fx, dataset.fy, dataset.cx, dataset.cy)
    training = np.asarray(dataset.split("train"))
    for index in dataset.split("val"):
        with torch.no_grad():
            rendered = render_frame(run, dataset.normalization.pose_to_original(dataset.poses[index]), camera)
        truth = np.asarray(dataset.images[index], np.float64)
        difference = rendered.rgb.numpy() - truth
        image_error = (difference**2).mean(axis=-1)
        error = image_error.ravel()
        directions = rays_of(dataset, index).directions.reshape(-1, 3).numpy().astype(np.float64)
        unseen = unseen_directions(directions, dataset, training)
        bias = difference.reshape(-1, 3).mean(axis=0)
        print(f"held-out {Path(dataset.image_names[index]).name}: PSNR {psnr(error.mean()):.2f} dB; "
              f"{unseen.mean():.1%} of its pixels look where no training photo does and carry "
              f"{error[unseen].sum() / error.sum():.1%} of its squared error; render - photo mean colour "
              f"{np.round(bias, 3).tolist()}, PSNR without it {psnr(((difference - bias) ** 2).mean()):.2f} "
              f"dB; squared error by {column_bands(image_error, args.column_splits)}")
    rng = np.random.default_rng(0)
    for index in training:
        rays = rays_of(dataset, index)
        pick = torch.as_tensor(rng.choice(dataset.width * dataset.height, args.pixels, replace=False))
        rendered = render_rays_chunked(run.model, rays.origins.reshape(-1, 3)[pick],
                                       rays.directions.reshape(-1, 3)[pick], run.scene, run.background,
                                       run.config.chunk_rays)
        truth = np.asarray(dataset.images[index], np.float64).reshape(-1, 3)[pick.numpy()]
        difference = rendered.rgb.numpy() - truth
        bias = np.round(difference.mean(axis=0), 3).tolist()
        print(f"training {Path(dataset.image_names[index]).name}: PSNR {psnr((difference**2).mean()):.2f} dB "
              f"on {args.pixels} pixels; render - photo mean colour {bias}")


if __name__ == "__main__":
    main()
