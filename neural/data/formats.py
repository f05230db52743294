"""Which loader reads a path, and the dataset as a training run sees it (background, size, scene)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from estimation.artefacts import TRANSFORMS_NAME
from neural.config import TrainConfig
from neural.data.blender import load_blender
from neural.data.bounds import unbounded_scene
from neural.data.dataset import SPLITS, Dataset
from neural.data.images import ImageLoading, ImageSize
from neural.data.npz import load_npz
from neural.data.reconstruction import load_reconstruction
from neural.errors import DatasetError

DatasetFormat = Literal["blender", "npz", "reconstruction"]
#: What each format defaults to where TrainConfig leaves it open: synthetic renders sit on a white, bounded
#: world; photographs have content all around them and no known background, and a reconstruction knows
#: the depth of its sparse points; few photos need a smoothness prior (model_options: per model, under the
#: user's own).
FORMAT_DEFAULTS: dict[str, dict[str, Any]] = {
    "blender": {"background": "white", "unbounded": False, "depth_supervision": False},
    "npz": {"background": "white", "unbounded": False, "depth_supervision": False},
    "reconstruction": {
        "background": "random",
        "unbounded": True,
        "depth_supervision": True,
        # Total variation on the grids: +0.66 dB on fountain-P11's held-out photos (300 steps, 400 px);
        # the distortion loss and per-photo appearance lost there and stay off. A 144^3 grid: +0.17-0.25 dB
        # there over 128^3 in 10 minutes at 800 px (its fewer steps cost less than its finer voxels gain;
        # half the voxels hold the contracted shell, which a thinner one cannot spare: -0.8 dB).
        "model_options": {
            "fast": {"tv_density_weight": 1e-4, "tv_color_weight": 1e-3, "final_voxels": 144**3},
        },
    },
}


def dataset_format(path: Path | str) -> DatasetFormat:
    """Which loader reads `path`: a tiny-NeRF .npz file, a Blender folder or a reconstruction folder."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such file or folder")
    if path.is_file():
        if path.suffix != ".npz":
            raise DatasetError(f"{path}: expected a .npz file or a dataset folder")
        return "npz"
    if any((path / f"transforms_{split}.json").is_file() for split in SPLITS):
        return "blender"
    if (path / TRANSFORMS_NAME).is_file():
        return "reconstruction"
    raise DatasetError(
        f"{path}: not a dataset folder (expected transforms_train.json / transforms_val.json, "
        "or transforms.json from `sfmnerf reconstruct`)"
    )


def load_dataset(
    path: Path | str,
    white_background: bool = True,
    unbounded: bool = False,
    image_size: ImageSize | None = None,
    cache_dir: Path | None = None,
    within: Path | None = None,
) -> Dataset:
    """Blender folder (transforms_{train,val,test}.json), tiny-NeRF .npz, or reconstruction folder.

    A Blender dataset's files must lie inside its folder; a reconstruction's inside `within` when given
    (the service: the reconstruction's job folder). image_size: load the images smaller (intrinsics scaled
    to match); resized image files are cached in cache_dir when given. unbounded: the scene reaches beyond
    its box (see `unbounded_scene`).
    """
    path = Path(path)
    sizing = ImageLoading(white_background, image_size, cache_dir)
    kind = dataset_format(path)
    if kind == "npz":
        dataset = load_npz(path, sizing)
    elif kind == "blender":
        dataset = load_blender(path, sizing)
    else:
        dataset = load_reconstruction(path, sizing, within)
    return unbounded_scene(dataset) if unbounded else dataset


def load_dataset_for(data: Path | str, config: TrainConfig, cache_dir: Path | None) -> Dataset:
    """The dataset as a run with this (data-resolved) config trains on it: background, size, scene."""
    return load_dataset(
        data,
        white_background=config.white_background,
        unbounded=bool(config.unbounded),
        image_size=ImageSize(config.max_side, config.downscale),
        cache_dir=cache_dir,
    )
