"""Writers (and readers, for round trips) of the reconstruction's files.

- COLMAP text model (`cameras.txt`, `images.txt`, `points3D.txt`): the camera (PINHOLE, SIMPLE_RADIAL,
  RADIAL or OPENCV with COLMAP's parameter order; one shared, or one per image), world-to-camera
  quaternion (qw qx qy qz) and translation per image, named by file name, point tracks and errors.
- PLY point cloud with colours (binary little-endian or ASCII).
- `transforms.json` in the nerfstudio / instant-ngp convention: camera-to-world in OpenGL axes.
- `depths.npz`: every observed point with its uncertainty along each viewing ray (`write_depths`), the
  depth supervision a radiance field trains with.

Conventions crossed here, once:
- Poses: `estimation` keeps world-to-camera (R, t) in OpenCV axes (x right, y down, z forward);
  COLMAP keeps the same; transforms.json wants camera-to-world in OpenGL axes (x right, y up, z back).
- Pixels: `estimation` uses OpenCV's pixel convention (the centre of the top-left pixel is (0, 0));
  COLMAP and nerfstudio put the top-left pixel's *corner* at (0, 0), so uv and the principal point
  gain PIXEL_CENTER_SHIFT = 0.5 on the way out (and lose it on the way back in).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from estimation.errors import InputError
from estimation.geometry.projection import COLMAP_MODEL_NAMES, Camera, CameraInput, as_camera, is_shared
from estimation.types import CameraPose

PIXEL_CENTER_SHIFT = 0.5
"""COLMAP/nerfstudio pixel = OpenCV pixel + 0.5 (corner vs centre of the top-left pixel at the origin)."""
COLMAP_CAMERA_ID = 1
OPENCV_TO_OPENGL_AXES = np.diag([1.0, -1.0, -1.0])
"""Flips camera y (down -> up) and z (forward -> backward): OpenCV <-> OpenGL camera axes."""
PLY_PROPERTIES = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]


# --- rotations ------------------------------------------------------------------------------------

def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (qw, qx, qy, qz), qw >= 0, with R = rotation of q (Shepperd's stable branch choice)."""
    R = np.asarray(R, float)
    trace = np.trace(R)
    diagonal = np.diag(R)
    if trace > diagonal.max():
        s = 2.0 * math.sqrt(1.0 + trace)
        q = np.array([s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    else:
        i = int(np.argmax(diagonal))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.empty(4)
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """R of the unit quaternion (qw, qx, qy, qz) (normalized first)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def opencv_pose_to_opengl_c2w(pose: CameraPose) -> np.ndarray:
    """4x4 camera-to-world in OpenGL camera axes: [R^T diag(1,-1,-1) | C] from world-to-camera (R, t)."""
    c2w = np.eye(4)
    c2w[:3, :3] = pose.R.T @ OPENCV_TO_OPENGL_AXES
    c2w[:3, 3] = pose.center
    return c2w


def opengl_c2w_to_opencv_pose(c2w: np.ndarray) -> CameraPose:
    """World-to-camera (R, t) in OpenCV axes from a 4x4 OpenGL camera-to-world (inverse of the above)."""
    c2w = np.asarray(c2w, float)
    R = (c2w[:3, :3] @ OPENCV_TO_OPENGL_AXES).T
    return CameraPose.from_center(R, c2w[:3, 3])


# --- COLMAP text ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP text model in `estimation`'s conventions (OpenCV pixels, world-to-camera poses).

    Images are keyed by COLMAP image id; points by COLMAP point id. Each image's observations are
    its POINTS2D (uv in OpenCV pixels) and the point id each belongs to (-1: none).
    """

    K: np.ndarray                               # the first camera's K
    width: int
    height: int
    cameras: dict[int, Camera]                  # camera id -> intrinsics (OpenCV pixels)
    image_camera_ids: dict[int, int]            # image id -> camera id
    image_names: dict[int, str]
    poses: dict[int, CameraPose]
    image_uv: dict[int, np.ndarray]             # (n_i, 2)
    image_point_ids: dict[int, np.ndarray]      # (n_i,)
    point_ids: np.ndarray                       # (P,)
    points: np.ndarray                          # (P, 3)
    colors: np.ndarray                          # (P, 3) uint8
    errors: np.ndarray                          # (P,)
    tracks: list[np.ndarray]                    # per point: (L, 2) of (image id, point2D index)


def _colmap_cameras(camera: CameraInput, image_indices: Sequence[int]
                    ) -> tuple[dict[int, Camera], dict[int, int]]:
    """(camera id -> Camera, image index -> camera id): id 1 when shared, image index + 1 per image."""
    if is_shared(camera):
        return {COLMAP_CAMERA_ID: as_camera(camera)}, dict.fromkeys(image_indices, COLMAP_CAMERA_ID)
    cameras = list(camera)
    return {m + 1: cameras[m] for m in image_indices}, {m: m + 1 for m in image_indices}


def _shift_principal_point(camera: Camera, shift: float) -> Camera:
    return replace(camera, cx=camera.cx + shift, cy=camera.cy + shift)


def colmap_camera_line(camera_id: int, camera: Camera, width: int, height: int) -> str:
    """`CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`, principal point moved to COLMAP's pixel convention."""
    params = " ".join(f"{v:.17g}" for v in _shift_principal_point(camera, PIXEL_CENTER_SHIFT).colmap_params())
    return f"{camera_id} {COLMAP_MODEL_NAMES[camera.model]} {width} {height} {params}"


def write_colmap_text(
    folder: Path,
    camera: CameraInput,
    width: int,
    height: int,
    image_names: Sequence[str],
    poses: Mapping[int, CameraPose],
    points: np.ndarray,
    colors: np.ndarray,
    errors: np.ndarray,
    obs_camera: np.ndarray,
    obs_point: np.ndarray,
    obs_uv: np.ndarray,
) -> None:
    """cameras.txt, images.txt, points3D.txt of the registered images (`poses` keyed by image index).

    `camera` is shared (one camera, id 1) or a list indexed by image index (camera id = image id).
    COLMAP image id = image index + 1, point id = point index + 1. Observation o says point
    obs_point[o] is seen by image obs_camera[o] at pixel obs_uv[o] (OpenCV convention).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    obs_camera = np.asarray(obs_camera, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    obs_uv = np.asarray(obs_uv, float).reshape(-1, 2)
    unknown = set(np.unique(obs_camera).tolist()) - set(poses)
    if unknown:
        raise ValueError(f"observations refer to unregistered image indices {sorted(unknown)}")

    cameras, camera_of_image = _colmap_cameras(camera, sorted(poses))
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: {len(cameras)}\n"
        + "".join(colmap_camera_line(camera_id, c, width, height) + "\n" for camera_id, c in cameras.items())
    )

    # The POINT2D_IDX of an observation is its position in its image's POINTS2D line.
    order = np.lexsort((obs_point, obs_camera))
    point2d_index = np.empty(len(obs_camera), np.int64)
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(poses)}, mean observations per image: "
        f"{len(obs_camera) / max(len(poses), 1):.4f}",
    ]
    for image_index in sorted(poses):
        pose = poses[image_index]
        q = rotation_to_quaternion(pose.R)
        lines.append(
            f"{image_index + 1} {' '.join(f'{v:.17g}' for v in q)} {' '.join(f'{v:.17g}' for v in pose.t)} "
            f"{camera_of_image[image_index]} {image_names[image_index]}"
        )
        in_image = order[obs_camera[order] == image_index]
        point2d_index[in_image] = np.arange(in_image.size)
        shifted = obs_uv[in_image] + PIXEL_CENTER_SHIFT
        # Python floats and ints (tolist) format twice as fast as numpy scalars.
        lines.append(" ".join(
            f"{u:.17g} {v:.17g} {p}" for u, v, p in zip(shifted[:, 0].tolist(), shifted[:, 1].tolist(),
                                                         (obs_point[in_image] + 1).tolist(), strict=True)
        ))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")

    points = np.asarray(points, float).reshape(-1, 3)
    track_lengths = np.bincount(obs_point, minlength=len(points))
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(points)}, mean track length: "
        f"{track_lengths.mean() if len(points) else 0.0:.4f}",
    ]
    by_point = np.argsort(obs_point, kind="stable")
    starts = np.concatenate([[0], np.cumsum(track_lengths)]).tolist()
    image_ids, point2d = (obs_camera[by_point] + 1).tolist(), point2d_index[by_point].tolist()
    rgb = np.asarray(colors, int).reshape(-1, 3).tolist()
    for p, ((x, y, z), (r, g, b), error) in enumerate(
            zip(points.tolist(), rgb, np.asarray(errors, float).tolist(), strict=True)):
        track = " ".join(f"{image_ids[k]} {point2d[k]}" for k in range(starts[p], starts[p + 1]))
        line = f"{p + 1} {x:.17g} {y:.17g} {z:.17g} {r} {g} {b} {error:.17g} {track}"
        lines.append(line.rstrip())
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the lines that are neither comments nor blank."""
    if not path.is_file():
        raise InputError(f"{path}: COLMAP file not found")
    return [(n, line) for n, line in enumerate(path.read_text().splitlines(), start=1)
            if line.strip() and not line.startswith("#")]


def _parse_numbers(path: Path, line_number: int, tokens: Sequence[str]) -> np.ndarray:
    try:
        return np.array([float(t) for t in tokens])
    except ValueError as error:
        raise InputError(f"{path}, line {line_number}: non-numeric value ({error})") from None


def read_colmap_text(folder: Path) -> ColmapModel:
    """A COLMAP text model written by `write_colmap_text`; InputError if malformed."""
    folder = Path(folder)
    cameras_path = folder / "cameras.txt"
    cameras, sizes = {}, set()
    for line_number, line in _data_lines(cameras_path):
        tokens = line.split()
        try:
            camera = Camera.from_colmap(tokens[1] if len(tokens) > 1 else "",
                                        _parse_numbers(cameras_path, line_number, tokens[4:]))
            camera_id, size = int(tokens[0]), (int(tokens[2]), int(tokens[3]))
        except ValueError as error:
            raise InputError(f"{cameras_path}, line {line_number}: {error}") from None
        cameras[camera_id] = _shift_principal_point(camera, -PIXEL_CENTER_SHIFT)
        sizes.add(size)
    if len(sizes) != 1:
        raise InputError(f"{cameras_path}: expected cameras of one image size, found {sorted(sizes)}")
    (width, height), = sizes
    K = next(iter(cameras.values())).K

    images_path = folder / "images.txt"
    if not images_path.is_file():
        raise InputError(f"{images_path}: COLMAP file not found")
    # Two lines per image; the second (POINTS2D) may be blank, so blank lines only separate images.
    image_lines = [(n, line) for n, line in enumerate(images_path.read_text().splitlines(), start=1)
                   if not line.startswith("#")]
    image_names, poses, image_uv, image_point_ids, image_camera_ids = {}, {}, {}, {}, {}
    cursor = 0
    while cursor < len(image_lines):
        pose_line, header = image_lines[cursor]
        if not header.strip():
            cursor += 1
            continue
        has_points_line = cursor + 1 < len(image_lines)
        points_line, points2d = image_lines[cursor + 1] if has_points_line else (pose_line + 1, "")
        cursor += 2
        tokens = header.split()
        if len(tokens) != 10:
            raise InputError(f"{images_path}, line {pose_line}: expected 10 values, found {len(tokens)}")
        image_id = int(tokens[0])
        values = _parse_numbers(images_path, pose_line, tokens[1:8])
        poses[image_id] = CameraPose(R=quaternion_to_rotation(values[:4]), t=values[4:7])
        image_names[image_id] = tokens[9]
        image_camera_ids[image_id] = int(tokens[8])
        triples = _parse_numbers(images_path, points_line, points2d.split())
        if triples.size % 3:
            raise InputError(f"{images_path}, line {points_line}: POINTS2D must be X, Y, POINT3D_ID triples")
        triples = triples.reshape(-1, 3)
        image_uv[image_id] = triples[:, :2] - PIXEL_CENTER_SHIFT
        image_point_ids[image_id] = triples[:, 2].astype(np.int64)

    points_path = folder / "points3D.txt"
    point_ids, points, colors, errors, tracks = [], [], [], [], []
    for line_number, line in _data_lines(points_path):
        values = _parse_numbers(points_path, line_number, line.split())
        if values.size < 8 or (values.size - 8) % 2:
            raise InputError(f"{points_path}, line {line_number}: malformed point line")
        point_ids.append(int(values[0]))
        points.append(values[1:4])
        colors.append(values[4:7])
        errors.append(values[7])
        tracks.append(values[8:].astype(np.int64).reshape(-1, 2))
    return ColmapModel(
        K=K, width=width, height=height, cameras=cameras, image_camera_ids=image_camera_ids,
        image_names=image_names, poses=poses, image_uv=image_uv,
        image_point_ids=image_point_ids, point_ids=np.array(point_ids, np.int64),
        points=np.array(points, float).reshape(-1, 3), colors=np.array(colors, np.uint8).reshape(-1, 3),
        errors=np.array(errors, float), tracks=tracks,
    )


# --- PLY ------------------------------------------------------------------------------------------

def write_ply(path: Path, points: np.ndarray, colors: np.ndarray, binary: bool = True) -> None:
    """Coloured point cloud: float32 x y z and uint8 red green blue per vertex."""
    points = np.asarray(points, float).reshape(-1, 3)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment written by sfmnerf\nelement vertex {len(points)}\n"
        + "".join(f"property {'float' if t == '<f4' else 'uchar'} {name}\n" for name, t in PLY_PROPERTIES)
        + "end_header\n"
    )
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as file:
        file.write(header.encode("ascii"))
        if binary:
            vertices = np.empty(len(points), dtype=PLY_PROPERTIES)
            for axis, name in enumerate("xyz"):
                vertices[name] = points[:, axis]
            for channel, name in enumerate(("red", "green", "blue")):
                vertices[name] = colors[:, channel]
            file.write(vertices.tobytes())
        else:
            file.write("".join(
                f"{x:.9g} {y:.9g} {z:.9g} {r} {g} {b}\n"
                for (x, y, z), (r, g, b) in zip(points.astype(np.float32), colors, strict=True)
            ).encode("ascii"))


PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
"""PLY scalar property types -> numpy type codes."""


def read_ply_vertices(path: Path) -> np.ndarray:
    """The vertex table (a structured array, one field per property) of an ASCII or binary little-endian PLY
    file, any scalar properties (not only `write_ply`'s); InputError naming the file if it cannot be read."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body = raw[raw.index(b"\n", end) + 1:] if b"\n" in raw[end:] else b""
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
                raise InputError(f"{path}: list properties on vertices are not supported")
            if words[1] not in PLY_TYPES:
                raise InputError(f"{path}: unknown PLY property type {words[1]!r}")
            properties.append((words[2], PLY_TYPES[words[1]]))
    dtype = np.dtype([(name, "<" + code) for name, code in properties])
    if fmt == "ascii":
        rows = body.decode("ascii", errors="replace").split("\n")[:count]
        try:
            values = [tuple(float(v) for v in row.split()[: len(properties)]) for row in rows]
        except ValueError as error:
            raise InputError(f"{path}: bad vertex row ({error})") from None
        if len(values) != count or any(len(row) != len(properties) for row in values):
            raise InputError(f"{path}: expected {count} vertex rows of {len(properties)} values")
        return np.array(values, dtype=dtype)
    if fmt == "binary_little_endian":
        if len(body) < count * dtype.itemsize:
            raise InputError(f"{path}: file ends before its {count} vertices")
        return np.frombuffer(body, dtype=dtype, count=count)
    raise InputError(f"{path}: unsupported PLY format {fmt!r} (ascii or binary_little_endian)")


def read_ply_points(path: Path) -> np.ndarray:
    """x, y, z of the vertices of a PLY file (`read_ply_vertices`); (P,3) float64."""
    vertices = read_ply_vertices(path)
    if not {"x", "y", "z"} <= set(vertices.dtype.names or ()):
        raise InputError(f"{path}: vertex element lacks x, y, z properties")
    return np.stack([vertices[axis].astype(np.float64) for axis in "xyz"], axis=1).reshape(-1, 3)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float, colors (N, 3) uint8) of a coloured PLY such as `write_ply` writes."""
    vertices = read_ply_vertices(path)
    channels = ("red", "green", "blue")
    if not set(channels) <= set(vertices.dtype.names or ()):
        raise InputError(f"{path}: vertex element lacks red, green, blue properties")
    colors = np.stack([vertices[name] for name in channels], axis=1).astype(np.uint8).reshape(-1, 3)
    return read_ply_points(path), colors


def read_colmap_points(path: Path) -> np.ndarray:
    """X, Y, Z columns of COLMAP's points3D.txt (POINT3D_ID X Y Z R G B ERROR TRACK...); (P,3)."""
    points = []
    for line_number, line in _data_lines(Path(path)):
        words = line.split()
        if len(words) < 4:
            raise InputError(f"{path}, line {line_number}: expected 'POINT3D_ID X Y Z ...'")
        points.append(_parse_numbers(Path(path), line_number, words[1:4]))
    return np.array(points, dtype=np.float64).reshape(-1, 3)


# --- depths.npz -----------------------------------------------------------------------------------

DEPTH_FIELDS = ("file_paths", "frame", "point", "sigma", "pixel_sigma")
"""The arrays of a depths file:
- file_paths (F,) str: the frames' file_path, as and in the order of transforms.json;
- frame (O,) int: which frame (index into file_paths) observes the point of observation o;
- point (O, 3) float: that point, in the world frame of transforms.json (its poses' units);
- sigma (O,) float > 0: the point's std-dev along that frame's viewing ray, same units:
  sqrt(r^T Sigma r), r the unit ray from the camera centre to the point, Sigma the point's marginal
  covariance from the final bundle adjustment scaled to the measured pixel noise;
- pixel_sigma () float > 0: that measured per-axis pixel noise."""


@dataclass(frozen=True)
class DepthObservations:
    """The content of a depths file (`DEPTH_FIELDS`)."""

    file_paths: list[str]
    frame: np.ndarray
    point: np.ndarray
    sigma: np.ndarray
    pixel_sigma: float


def write_depths(path: Path, depths: DepthObservations) -> None:
    """depths.npz (`DEPTH_FIELDS`), uncompressed; read back by `read_depths`."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as file:
        np.savez(file, file_paths=np.array(depths.file_paths, dtype=str),
                 frame=np.asarray(depths.frame, np.int64), point=np.asarray(depths.point, np.float64),
                 sigma=np.asarray(depths.sigma, np.float64), pixel_sigma=np.float64(depths.pixel_sigma))


def read_depths(path: Path) -> DepthObservations:
    """A depths file, checked: InputError naming the file and the field that is missing, misshapen,
    out of range, not finite, or (sigma, pixel_sigma) not positive."""
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise InputError(f"{path}: not a depths file ({error})") from None
    with archive:
        missing = [name for name in DEPTH_FIELDS if name not in archive.files]
        if missing:
            raise InputError(f"{path}: missing field {missing[0]!r}")
        arrays = {name: archive[name] for name in DEPTH_FIELDS}
    file_paths, frame, point = arrays["file_paths"], arrays["frame"], arrays["point"]
    sigma, pixel_sigma = arrays["sigma"], arrays["pixel_sigma"]
    count = len(frame) if frame.ndim == 1 else -1
    expected = {"file_paths": (file_paths.ndim == 1 and file_paths.dtype.kind == "U", "(F,) strings"),
                "frame": (frame.ndim == 1 and frame.dtype.kind in "iu", "(O,) integers"),
                "point": (point.shape == (count, 3) and point.dtype.kind == "f", "(O, 3) floats"),
                "sigma": (sigma.shape == (count,) and sigma.dtype.kind == "f", "(O,) floats"),
                "pixel_sigma": (pixel_sigma.shape == () and pixel_sigma.dtype.kind == "f", "one float")}
    for name, (ok, shape) in expected.items():
        if not ok:
            raise InputError(f"{path}: field {name!r} must be {shape}, got {arrays[name].dtype} "
                             f"{arrays[name].shape}")
    if len(frame) and (frame.min() < 0 or frame.max() >= len(file_paths)):
        raise InputError(f"{path}: field 'frame' refers to frames outside 0..{len(file_paths) - 1}")
    for name in ("point", "sigma", "pixel_sigma"):
        if not np.all(np.isfinite(arrays[name])):
            raise InputError(f"{path}: field {name!r} has non-finite values")
    for name in ("sigma", "pixel_sigma"):
        if not np.all(arrays[name] > 0):
            raise InputError(f"{path}: field {name!r} must be positive")
    return DepthObservations(file_paths.tolist(), frame.astype(np.int64), point.astype(np.float64),
                             sigma.astype(np.float64), float(pixel_sigma))


# --- transforms.json ------------------------------------------------------------------------------

def _intrinsics_fields(camera: Camera) -> dict:
    """fl_x fl_y cx cy k1 k2 p1 p2 of nerfstudio's OPENCV model (every model here is a special case)."""
    return {"fl_x": float(camera.fx), "fl_y": float(camera.fy),
            "cx": float(camera.cx) + PIXEL_CENTER_SHIFT, "cy": float(camera.cy) + PIXEL_CENTER_SHIFT,
            "k1": float(camera.k1), "k2": float(camera.k2), "p1": float(camera.p1), "p2": float(camera.p2)}


def transforms_dict(
    camera: Camera | np.ndarray,
    width: int,
    height: int,
    frames: Sequence[tuple[str, CameraPose]],
    ply_file_path: str | None = None,
    frame_cameras: Sequence[Camera] | None = None,
) -> dict:
    """nerfstudio / instant-ngp `transforms.json` content; frames = (file_path, world-to-camera pose).

    `camera` (a Camera or 3x3 K) gives the file's intrinsics; `frame_cameras` (one per frame, for
    per-image cameras) adds each frame's own, which nerfstudio prefers over the file's."""
    camera = as_camera(camera)
    content = {
        "camera_model": "OPENCV",
        **_intrinsics_fields(camera),
        "w": int(width),
        "h": int(height),
        "camera_angle_x": 2 * math.atan(width / (2 * float(camera.fx))),
        "camera_angle_y": 2 * math.atan(height / (2 * float(camera.fy))),
        "frames": [
            {"file_path": file_path, "transform_matrix": opencv_pose_to_opengl_c2w(pose).tolist(),
             **(_intrinsics_fields(frame_cameras[f]) if frame_cameras is not None else {})}
            for f, (file_path, pose) in enumerate(frames)
        ],
    }
    if ply_file_path is not None:
        content["ply_file_path"] = ply_file_path
    return content


def write_json(path: Path, content: dict) -> None:
    """Pretty-printed JSON (numpy arrays and scalars converted)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(content, indent=2, default=_json_default) + "\n")


def _json_default(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")
