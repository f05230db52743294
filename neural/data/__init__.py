"""One typed dataset for three inputs: Blender folders, tiny-NeRF .npz files and `sfmnerf reconstruct` output.

- `dataset`: the `Dataset` every loader returns; `formats`: which loader reads a path (`load_dataset`);
- `blender`, `npz`, `reconstruction`: the three readers; `images`: image files, smaller sizes, the cache;
- `bounds`: a reconstruction's normalization and near/far from its points, unbounded scenes;
- `files`: JSON, keys, rigid poses and confined paths, shared by the readers.
The PLY and COLMAP readers live beside their writers in `estimation.io.export`.
"""

from neural.data.bounds import unbounded_scene
from neural.data.dataset import SPLITS, Dataset
from neural.data.files import check_rigid_pose, read_json, require
from neural.data.formats import FORMAT_DEFAULTS, DatasetFormat, dataset_format, load_dataset, load_dataset_for
from neural.data.images import ImageLoading, ImageSize, load_image

__all__ = [
    "FORMAT_DEFAULTS",
    "SPLITS",
    "Dataset",
    "DatasetFormat",
    "ImageLoading",
    "ImageSize",
    "check_rigid_pose",
    "dataset_format",
    "load_dataset",
    "load_dataset_for",
    "load_image",
    "read_json",
    "require",
    "unbounded_scene",
]
