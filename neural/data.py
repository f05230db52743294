"""One typed dataset for three inputs: Blender folders, tiny-NeRF .npz files and `sfmnerf reconstruct` output.

Conventions: poses are camera-to-world (4,4) in OpenGL camera axes; intrinsics are pixels; images are
float32 RGB in [0,1], RGBA composited on white (or black) once, here. A reconstruction's scene is
re-centred and scaled into the normalized scene frame (recorded as `normalization`), the other formats
keep their own frame. Images can be loaded at a reduced size (`ImageSize`, intrinsics scaled with them,
resized files cached by content key), and any scene can be made unbounded (`unbounded_scene`).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from PIL import Image

from neural.config import TrainConfig
from neural.errors import DatasetError
from neural.scene import SceneInfo, SceneNormalization
from neural.undistortion import camera_from_transforms, pinhole_target, resample_to, to_nerfstudio_intrinsics

SPLITS: tuple[str, ...] = ("train", "val", "test")
#: The NeRF-synthetic convention for Blender scenes and tiny-NeRF files without their own bounds.
SYNTHETIC_NEAR, SYNTHETIC_FAR = 2.0, 6.0
SYNTHETIC_BOX_HALF_SIZE = 1.5
#: Largest deviation of R^T R from I (and of det R from 1) accepted for a rigid pose.
RIGID_TOLERANCE = 1e-3
#: Percentiles of the sparse points that bound a reconstruction's box (robust to stray points).
POINT_BOX_PERCENTILES = (2.0, 98.0)
#: The box is enlarged by this factor around its centre, then scaled to fit [-1, 1]^3.
POINT_BOX_PADDING = 1.2
#: Near/far are this factor outside the closest / farthest sparse point seen in front of any camera.
DEPTH_MARGIN = 0.8
#: A reconstruction without listed splits holds out every HOLDOUT_EVERY-th frame for validation (LLFF).
HOLDOUT_EVERY = 8
#: An unbounded scene's far bound, in half-sides of its inner cube (contracted to 2 - 1/1000 of the cube).
UNBOUNDED_FAR_HALF_SIDES = 1000.0
#: Bumped when the cached resized images would change.
IMAGE_CACHE_VERSION = 1

DatasetFormat = Literal["blender", "npz", "reconstruction"]
#: What each format defaults to where TrainConfig leaves it open: synthetic renders sit on a white, bounded
#: world; photographs have content all around them and no known background.
FORMAT_DEFAULTS: dict[str, dict[str, Any]] = {
    "blender": {"background": "white", "unbounded": False},
    "npz": {"background": "white", "unbounded": False},
    "reconstruction": {"background": "random", "unbounded": True},
}


@dataclass(frozen=True)
class ImageSize:
    """Load images smaller: at most `max_side` pixels on their longer side, or `downscale` times smaller."""

    max_side: int | None = None
    downscale: float | None = None

    def target(self, width: int, height: int) -> tuple[int, int]:
        """(W', H') = round(s W), round(s H), s = min(1, max_side / max(W, H)) or 1 / downscale."""
        scale = 1.0
        if self.max_side is not None:
            scale = min(scale, self.max_side / max(width, height))
        if self.downscale is not None:
            scale = min(scale, 1.0 / self.downscale)
        return max(1, round(width * scale)), max(1, round(height * scale))


@dataclass
class Dataset:
    """Posed images of one scene with their split indices and scene bounds."""

    images: np.ndarray  # (N,H,W,3) float32 in [0,1]
    poses: np.ndarray  # (N,4,4) float32 camera-to-world, OpenGL axes, scene frame
    fx: float
    fy: float
    cx: float
    cy: float
    scene: SceneInfo
    splits: dict[str, np.ndarray]  # split name -> indices into images
    image_names: list[str]
    source: Path
    white_background: bool = True
    normalization: SceneNormalization = field(default_factory=SceneNormalization)

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def near(self) -> float:
        return self.scene.near

    @property
    def far(self) -> float:
        return self.scene.far

    def split(self, name: str) -> np.ndarray:
        """Indices of split `name`; DatasetError if it is absent or empty."""
        indices = self.splits.get(name)
        if indices is None or len(indices) == 0:
            have = ", ".join(f"{k} ({len(v)})" for k, v in self.splits.items())
            raise DatasetError(f"{self.source}: split {name!r} is empty or missing (splits: {have})")
        return indices


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
    if (path / "transforms.json").is_file():
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


def unbounded_scene(dataset: Dataset) -> Dataset:
    """The dataset with an unbounded scene: its box grown to hold every camera, far pushed out to
    UNBOUNDED_FAR_HALF_SIDES half-sides of that box's cube (content beyond the box lives in contracted space).
    """
    centres = dataset.poses[:, :3, 3].astype(np.float64)
    low = np.minimum(np.asarray(dataset.scene.scene_box_min), centres.min(axis=0))
    high = np.maximum(np.asarray(dataset.scene.scene_box_max), centres.max(axis=0))
    half_side = 0.5 * float((high - low).max())
    scene = SceneInfo(
        near=dataset.scene.near,
        far=max(UNBOUNDED_FAR_HALF_SIDES * half_side, 2.0 * dataset.scene.far),
        scene_box_min=tuple(low.tolist()),
        scene_box_max=tuple(high.tolist()),
        unbounded=True,
    )
    return replace(dataset, scene=scene)


# ----------------------------------------------------------------------------------------------------------
# Checks and small readers


def check_rigid_pose(c2w: np.ndarray, where: str) -> np.ndarray:
    """c2w must be [[R, t], [0, 0, 0, 1]] with R^T R = I and det R = 1; returns it as float64 (4,4)."""
    try:
        matrix = np.asarray(c2w, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{where}: transform_matrix is not numeric ({error})") from None
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise DatasetError(f"{where}: transform_matrix must be 4x4, got shape {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise DatasetError(f"{where}: transform_matrix has non-finite entries")
    if not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=RIGID_TOLERANCE):
        raise DatasetError(
            f"{where}: transform_matrix last row must be [0, 0, 0, 1], got {matrix[3].tolist()}"
        )
    rotation = matrix[:3, :3]
    orthogonality = np.abs(rotation.T @ rotation - np.eye(3)).max()
    determinant = np.linalg.det(rotation)
    if orthogonality > RIGID_TOLERANCE or abs(determinant - 1.0) > RIGID_TOLERANCE:
        raise DatasetError(
            f"{where}: transform_matrix is not a rigid transform "
            f"(|R^T R - I| = {orthogonality:.3g}, det R = {determinant:.4g})"
        )
    return matrix


def read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise DatasetError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def require(data: dict[str, Any], key: str, where: Path | str) -> Any:
    if key not in data:
        raise DatasetError(f"{where}: missing key {key!r}")
    return data[key]


def load_image(path: Path, white_background: bool) -> np.ndarray:
    """RGB(A) image file -> (H,W,3) float32 in [0,1]; RGBA is composited: rgb a + background (1 - a)."""
    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    try:
        with Image.open(path) as image:
            has_alpha = image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info)
            pixels = np.asarray(image.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as error:
        # Above Pillow's MAX_IMAGE_PIXELS (a warning becomes this error where warnings are errors).
        raise DatasetError(f"{path}: more pixels than the limit {Image.MAX_IMAGE_PIXELS}") from error
    except OSError as error:
        raise DatasetError(f"{path}: cannot read image ({error})") from None
    if not has_alpha:
        return pixels
    rgb, alpha = pixels[..., :3], pixels[..., 3:]
    background = 1.0 if white_background else 0.0
    return rgb * alpha + background * (1.0 - alpha)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H,W,C) float image resampled to (height, width, C) by area averaging (PIL's box filter)."""
    if image.shape[:2] == (height, width):
        return image
    channels = [
        np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c], np.float32), mode="F").resize(
            (width, height), Image.Resampling.BOX
        ))
        for c in range(image.shape[-1])
    ]  # fmt: skip
    return np.stack(channels, axis=-1)


@dataclass(frozen=True)
class ImageLoading:
    """How a loader reads image files: the RGBA background, an optional smaller size, a cache folder."""

    white_background: bool = True
    image_size: ImageSize | None = None
    cache_dir: Path | None = None

    def size_for(self, width: int, height: int) -> tuple[int, int]:
        return (width, height) if self.image_size is None else self.image_size.target(width, height)

    def load(self, path: Path) -> tuple[np.ndarray, tuple[int, int]]:
        """The image at its loading size and its file's (width, height).

        Resized images are rounded to float16 (whether cached or not, so both give the same values) and,
        with a cache_dir, kept as CACHE/<key>.npy; the key hashes the file's path, size and mtime, the
        target size and the background, so a changed file is decoded afresh.
        """
        if self.image_size is None:  # full size: load_image's own checks and errors, nothing else
            image = load_image(path, self.white_background)
            return image, (image.shape[1], image.shape[0])
        if not path.is_file():
            raise DatasetError(f"{path}: image file not found")
        try:
            with Image.open(path) as header:
                original = header.size
        except (Image.DecompressionBombError, Image.DecompressionBombWarning) as error:
            raise DatasetError(f"{path}: more pixels than the limit {Image.MAX_IMAGE_PIXELS}") from error
        except OSError as error:
            raise DatasetError(f"{path}: cannot read image ({error})") from None
        width, height = self.size_for(*original)
        if (width, height) == original:
            return load_image(path, self.white_background), original
        cached = None
        if self.cache_dir is not None:
            stat = path.stat()
            key = json.dumps(
                [IMAGE_CACHE_VERSION, str(path.resolve()), stat.st_size, stat.st_mtime_ns, width, height,
                 self.white_background]
            )  # fmt: skip
            cached = self.cache_dir / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.npy"
            if cached.is_file():
                return np.load(cached).astype(np.float32), original
        small = resize_image(load_image(path, self.white_background), width, height).astype(np.float16)
        if cached is not None:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            temporary = cached.with_suffix(".tmp.npy")
            np.save(temporary, small)
            temporary.replace(cached)
        return small.astype(np.float32), original


def check_same_size(image: np.ndarray, name: str, first: np.ndarray, first_name: str) -> None:
    """DatasetError naming `name` if its size differs from the first image's."""
    if image.shape != first.shape:
        raise DatasetError(
            f"{name}: image size {image.shape[1]}x{image.shape[0]} differs from "
            f"{first.shape[1]}x{first.shape[0]} of {first_name}; all images must have one size"
        )


def confined_path(root: Path, file_path: Any, where: str, within: Path | None) -> Path:
    """root / file_path resolved (links followed); DatasetError naming `where` if it leaves `within`.

    The message is the same whether the target exists or not, so a dataset cannot probe the file system.
    `within` None: no bound (a local reconstruction's images may live anywhere).
    """
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{where}: file_path must be a non-empty string")
    candidate = (root / file_path).resolve()
    if within is not None and not candidate.is_relative_to(within.resolve()):
        raise DatasetError(f"{where}: file_path {file_path!r} points outside the dataset folder; refused")
    return candidate


def image_path(root: Path, file_path: str, where: str, within: Path | None) -> Path:
    """A frame's file_path relative to root, bounded by `within`; Blender's have no extension (then .png)."""
    candidate = confined_path(root, file_path, where, within)
    if candidate.suffix.lower() in (".png", ".jpg", ".jpeg") or candidate.is_file():
        return candidate
    return confined_path(root, f"{file_path}.png", where, within)


def synthetic_dataset(
    images: np.ndarray,
    poses: np.ndarray,
    focal: float,
    near: float,
    far: float,
    splits: dict[str, np.ndarray],
    image_names: list[str],
    source: Path,
    white_background: bool = True,
    original_size: tuple[int, int] | None = None,
) -> Dataset:
    """A NeRF-synthetic scene: one pinhole focal, principal point at the image centre, the fixed scene box.

    focal is for images of original_size (width, height; default: as loaded), scaled to the loaded size.
    """
    height, width = images.shape[1:3]
    original_width, original_height = original_size or (width, height)
    half = SYNTHETIC_BOX_HALF_SIZE
    return Dataset(
        images=images,
        poses=poses.astype(np.float32),
        fx=focal * width / original_width,
        fy=focal * height / original_height,
        cx=width / 2.0,
        cy=height / 2.0,
        scene=SceneInfo(
            near=near, far=far, scene_box_min=(-half, -half, -half), scene_box_max=(half, half, half)
        ),
        splits=splits,
        image_names=image_names,
        source=source,
        white_background=white_background,
    )


# ----------------------------------------------------------------------------------------------------------
# Blender


def load_blender(root: Path, loading: ImageLoading = ImageLoading()) -> Dataset:
    """transforms_{split}.json (camera_angle_x or fl_x, frames[file_path, transform_matrix]) + RGBA PNGs."""
    images: list[np.ndarray] = []
    original_sizes: list[tuple[int, int]] = []
    poses: list[np.ndarray] = []
    names: list[str] = []
    splits: dict[str, np.ndarray] = {}
    focal: float | None = None
    near, far = SYNTHETIC_NEAR, SYNTHETIC_FAR
    for split in SPLITS:
        json_path = root / f"transforms_{split}.json"
        if not json_path.is_file():
            continue
        meta = read_json(json_path)
        frames = require(meta, "frames", json_path)
        if not isinstance(frames, list) or not frames:
            raise DatasetError(f"{json_path}: 'frames' is empty; the {split} split has no images")
        near, far = float(meta.get("near", near)), float(meta.get("far", far))
        start = len(images)
        for index, frame in enumerate(frames):
            where = f"{json_path} frames[{index}]"
            file_path = require(frame, "file_path", where)
            poses.append(
                check_rigid_pose(require(frame, "transform_matrix", where), f"{where} ({file_path})")
            )
            image, original_size = loading.load(image_path(root, file_path, where, within=root))
            images.append(image)
            original_sizes.append(original_size)
            names.append(str(file_path))
            check_same_size(images[-1], names[-1], images[0], names[0])
        splits[split] = np.arange(start, len(images))
        width = original_sizes[start][0]
        split_focal = focal_from_meta(meta, width, json_path)
        if focal is not None and not math.isclose(focal, split_focal, rel_tol=1e-4):
            raise DatasetError(
                f"{json_path}: focal {split_focal:.4f} differs from the other splits' {focal:.4f}"
            )
        focal = split_focal
    assert focal is not None
    return synthetic_dataset(
        np.stack(images), np.stack(poses), focal, near, far, splits, names, root, loading.white_background,
        original_sizes[0],
    )  # fmt: skip


def focal_from_meta(meta: dict[str, Any], width: int, where: Path) -> float:
    """fx = fl_x if given, else 0.5 W / tan(0.5 camera_angle_x)."""
    if "fl_x" in meta:
        return float(meta["fl_x"])
    if "camera_angle_x" not in meta:
        raise DatasetError(f"{where}: missing key 'camera_angle_x' (or 'fl_x')")
    return 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))


# ----------------------------------------------------------------------------------------------------------
# tiny-NeRF .npz


def load_npz(path: Path, loading: ImageLoading = ImageLoading()) -> Dataset:
    """images (N,H,W,3) in [0,1], poses (N,4,4) c2w, focal; optional split (0/1/2: train/val/test), near/far.

    Without `split`, every tenth image (index % 10 == 9) is held out for validation. RGBA arrays are
    composited on white (the format's convention); `loading` may shrink the images (never cached: they are
    in memory already).
    """
    try:
        archive = np.load(path)
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read the .npz file ({error})") from None
    with archive:
        for key in ("images", "poses", "focal"):
            if key not in archive:
                raise DatasetError(f"{path}: missing array {key!r} (have {', '.join(archive.files)})")
        images = np.asarray(archive["images"], dtype=np.float32)
        poses = np.asarray(archive["poses"], dtype=np.float64)
        focal = float(np.asarray(archive["focal"]).reshape(-1)[0])
        split_codes = np.asarray(archive["split"]) if "split" in archive else None
        near = float(archive["near"]) if "near" in archive else SYNTHETIC_NEAR
        far = float(archive["far"]) if "far" in archive else SYNTHETIC_FAR
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise DatasetError(f"{path}: 'images' must be (N,H,W,3), got shape {images.shape}")
    if images.shape[-1] == 4:  # composite on white, the format's convention
        images = images[..., :3] * images[..., 3:] + (1.0 - images[..., 3:])
    if poses.shape[0] != images.shape[0]:
        raise DatasetError(f"{path}: {images.shape[0]} images but {poses.shape[0]} 'poses'")
    checked = np.stack([check_rigid_pose(pose, f"{path} poses[{i}]") for i, pose in enumerate(poses)])
    count = images.shape[0]
    if split_codes is None:
        is_val = np.arange(count) % 10 == 9
        split_codes = np.where(is_val, 1, 0)
    if split_codes.shape != (count,):
        raise DatasetError(
            f"{path}: 'split' must have one entry per image ({count}), got {split_codes.shape}"
        )
    splits = {name: np.flatnonzero(split_codes == code) for code, name in enumerate(SPLITS)}
    splits = {name: indices for name, indices in splits.items() if len(indices)}
    if "train" not in splits:
        raise DatasetError(f"{path}: 'split' has no training images (code 0)")
    names = [f"{path.stem}[{i}]" for i in range(count)]
    original_size = (images.shape[2], images.shape[1])
    width, height = loading.size_for(*original_size)
    images = np.stack([resize_image(image, width, height) for image in np.clip(images, 0.0, 1.0)])
    return synthetic_dataset(
        images, checked, focal, near, far, splits, names, path, original_size=original_size
    )


# ----------------------------------------------------------------------------------------------------------
# `sfmnerf reconstruct` output


def read_ply_points(path: Path) -> np.ndarray:
    """x, y, z of the vertices of an ASCII or binary little-endian PLY file; (P,3) float64."""
    ply_types = {
        "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
        "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
        "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
    }  # fmt: skip
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[raw.index(b"\n", end) + 1 :]
    fmt, count, properties, in_vertex = "", 0, [], False
    for line in header:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
        elif words[0] == "property" and in_vertex:
            if words[1] == "list":
                raise DatasetError(f"{path}: list properties on vertices are not supported")
            if words[1] not in ply_types:
                raise DatasetError(f"{path}: unknown PLY property type {words[1]!r}")
            properties.append((words[2], ply_types[words[1]]))
    names = [name for name, _ in properties]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{path}: vertex element lacks x, y, z properties")
    if fmt == "ascii":
        rows = body.decode("ascii", errors="replace").split("\n")[:count]
        try:
            table = np.array(
                [[float(v) for v in row.split()[: len(names)]] for row in rows], dtype=np.float64
            )
        except ValueError as error:
            raise DatasetError(f"{path}: bad vertex row ({error})") from None
        if table.shape != (count, len(names)):
            raise DatasetError(f"{path}: expected {count} vertex rows of {len(names)} values")
        return table[:, [names.index(axis) for axis in "xyz"]]
    if fmt == "binary_little_endian":
        dtype = np.dtype([(name, "<" + code) for name, code in properties])
        if len(body) < count * dtype.itemsize:
            raise DatasetError(f"{path}: file ends before its {count} vertices")
        table = np.frombuffer(body, dtype=dtype, count=count)
        return np.stack([table[axis].astype(np.float64) for axis in "xyz"], axis=1)
    raise DatasetError(f"{path}: unsupported PLY format {fmt!r} (ascii or binary_little_endian)")


def read_colmap_points(path: Path) -> np.ndarray:
    """X, Y, Z columns of COLMAP's points3D.txt (POINT3D_ID X Y Z R G B ERROR TRACK...); (P,3)."""
    points = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        words = line.split()
        try:
            points.append([float(words[1]), float(words[2]), float(words[3])])
        except (IndexError, ValueError):
            raise DatasetError(f"{path}:{number}: expected 'POINT3D_ID X Y Z ...'") from None
    return np.array(points, dtype=np.float64).reshape(-1, 3)


def sparse_points(root: Path) -> np.ndarray:
    """The reconstruction's sparse points from points.ply, else sparse/points3D.txt."""
    for candidate, reader in (
        (root / "points.ply", read_ply_points),
        (root / "sparse/points3D.txt", read_colmap_points),
    ):
        if candidate.is_file():
            points = reader(candidate)
            if len(points) < 4:
                raise DatasetError(f"{candidate}: {len(points)} points; need at least 4 to bound the scene")
            return points
    raise DatasetError(f"{root}: no points.ply or sparse/points3D.txt to bound the scene with")


def normalization_from_points(points: np.ndarray) -> tuple[SceneNormalization, np.ndarray, np.ndarray]:
    """Centre the robust box of the points at 0 and scale its padded half-extent to 1; box in scene frame."""
    low, high = np.percentile(points, POINT_BOX_PERCENTILES, axis=0)
    centre = 0.5 * (low + high)
    half_extent = 0.5 * (high - low).max() * POINT_BOX_PADDING
    if half_extent <= 0:
        raise DatasetError("the sparse points are all at one place; cannot bound the scene")
    normalization = SceneNormalization(centre=tuple(float(c) for c in centre), scale=float(1.0 / half_extent))
    box_low = normalization.points_to_scene(centre - POINT_BOX_PADDING * 0.5 * (high - low))
    box_high = normalization.points_to_scene(centre + POINT_BOX_PADDING * 0.5 * (high - low))
    return normalization, box_low, box_high


def near_far_from_points(poses: np.ndarray, points: np.ndarray) -> tuple[float, float]:
    """Near/far = margins around the closest/farthest point in front of any camera (along -z, OpenGL)."""
    distances = []
    for c2w in poses:
        relative = points - c2w[:3, 3]
        in_front = relative @ (-c2w[:3, 2]) > 0
        distances.append(np.linalg.norm(relative[in_front], axis=1))
    all_distances = np.concatenate(distances)
    if all_distances.size == 0:
        raise DatasetError("no sparse point lies in front of any camera; poses and points disagree")
    low, high = np.percentile(all_distances, [1.0, 99.0])
    return float(low * DEPTH_MARGIN), float(high / DEPTH_MARGIN)


def load_reconstruction(
    root: Path, loading: ImageLoading = ImageLoading(), within: Path | None = None
) -> Dataset:
    """transforms.json (fl_x, fl_y, cx, cy, w, h, frames[file_path, transform_matrix]) + images + points.

    Image files must lie inside `within` when given. Loaded smaller, the intrinsics scale with the image:
    f' = f W'/W, c' = c W'/W per axis (pixel centres at +0.5 map onto each other because the image edges do).
    Photos with distortion (k1 k2 p1 p2) or intrinsics of their own are resampled into one pinhole camera
    (neural.undistortion), so the dataset's K describes every image.
    """
    json_path = root / "transforms.json"
    meta = read_json(json_path)
    frames = require(meta, "frames", json_path)
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{json_path}: 'frames' is empty")
    width, height = int(require(meta, "w", json_path)), int(require(meta, "h", json_path))
    loaded_width, loaded_height = loading.size_for(width, height)
    scale = (loaded_width / width, loaded_height / height)
    file_camera = camera_from_transforms(meta, width, height, scale, str(json_path))
    images, poses, names, photo_cameras = [], [], [], []
    for index, frame in enumerate(frames):
        where = f"{json_path} frames[{index}]"
        file_path = require(frame, "file_path", where)
        photo_cameras.append(camera_from_transforms({**meta, **frame}, width, height, scale, where))
        poses.append(check_rigid_pose(require(frame, "transform_matrix", where), f"{where} ({file_path})"))
        image, original_size = loading.load(image_path(root, file_path, where, within))
        if original_size != (width, height):
            raise DatasetError(
                f"{root / file_path}: image size {original_size[0]}x{original_size[1]} differs from "
                f"w x h = {width}x{height} in {json_path}"
            )
        images.append(image)
        names.append(str(file_path))
    original_poses = np.stack(poses)
    points = sparse_points(root)
    normalization, box_low, box_high = normalization_from_points(points)
    scene_poses = normalization.pose_to_scene(original_poses)
    near, far = near_far_from_points(scene_poses, normalization.points_to_scene(points))
    scene = SceneInfo(
        near=near, far=far, scene_box_min=tuple(box_low.tolist()), scene_box_max=tuple(box_high.tolist())
    )
    target = file_camera
    if file_camera.model != "pinhole" or any(camera != file_camera for camera in photo_cameras):
        target = pinhole_target(file_camera, photo_cameras, loaded_width, loaded_height, str(json_path))
        images = [resample_to(image, camera, target)
                  for image, camera in zip(images, photo_cameras, strict=True)]
    fx, fy, cx, cy = to_nerfstudio_intrinsics(target)
    return Dataset(
        images=np.stack(images),
        poses=scene_poses.astype(np.float32),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        scene=scene,
        splits=reconstruction_splits(meta, names, json_path),
        image_names=names,
        source=root,
        white_background=loading.white_background,
        normalization=normalization,
    )


def reconstruction_splits(meta: dict[str, Any], names: list[str], where: Path) -> dict[str, np.ndarray]:
    """Splits from `train_filenames`/`val_filenames`/`test_filenames` if listed (nerfstudio), else a holdout.

    Without lists, the LLFF convention: frames 0, HOLDOUT_EVERY, 2 HOLDOUT_EVERY, ... are held out for
    validation (at least one, so every reconstruction of two or more frames is evaluated on views it never
    trained on).
    """
    listed = {split: meta.get(f"{split}_filenames") for split in SPLITS}
    if any(value is not None for value in listed.values()):
        index_of = {name: i for i, name in enumerate(names)}
        splits = {}
        for split, files in listed.items():
            if files is None:
                continue
            missing = [f for f in files if f not in index_of]
            if missing:
                raise DatasetError(f"{where}: {split}_filenames names {missing[0]!r}, which no frame has")
            splits[split] = np.array([index_of[f] for f in files], dtype=np.int64)
        return splits
    all_indices = np.arange(len(names))
    if len(names) < 2:
        raise DatasetError(f"{where}: one frame; a held-out view needs at least two")
    is_val = all_indices % HOLDOUT_EVERY == 0
    return {"train": all_indices[~is_val], "val": all_indices[is_val]}
