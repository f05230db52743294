"""The camera model and the one projection every estimator and the bundle adjustment share.

A `Camera` is one of COLMAP's models, with COLMAP's parameter names:

- pinhole:        fx, fy, cx, cy
- simple-radial:  f (= fx = fy), cx, cy, k1
- radial:         f (= fx = fy), cx, cy, k1, k2
- opencv:         fx, fy, cx, cy, k1, k2, p1, p2

All four are OpenCV's radial-tangential model with some coefficients held at zero. A point in camera
coordinates x_cam = R X + t (world-to-camera) has normalized coordinates x = x_cam[:2] / x_cam[2],
distorted ones x_d = x (1 + k1 r^2 + k2 r^4) + tangential(p1, p2), r^2 = |x|^2, and pixels
u = fx x_d + skew y_d + cx, v = fy y_d + cy. Pixels are in the project's convention (the centre of
the top-left pixel is (0, 0), as OpenCV); exports add 0.5 for COLMAP/nerfstudio, once.
`skew` only comes from a calibration file's K[0, 1] (COLMAP's models have none).

Every function is vectorized over points; a Camera whose fields are arrays (see `Camera.take`)
gives each point its own intrinsics (per-image cameras).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Literal, NamedTuple, get_args

import numpy as np

CameraModel = Literal["pinhole", "simple-radial", "radial", "opencv"]
CAMERA_MODELS: tuple[str, ...] = get_args(CameraModel)
COLMAP_MODEL_NAMES = {"pinhole": "PINHOLE", "simple-radial": "SIMPLE_RADIAL", "radial": "RADIAL",
                      "opencv": "OPENCV"}
COLMAP_PARAMETERS = {
    "pinhole": ("fx", "fy", "cx", "cy"),
    "simple-radial": ("f", "cx", "cy", "k1"),
    "radial": ("f", "cx", "cy", "k1", "k2"),
    "opencv": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
"""Each model's parameters in COLMAP's order (`f` is fx = fy)."""
DISTORTION_PARAMETERS = {"pinhole": (), "simple-radial": ("k1",), "radial": ("k1", "k2"),
                         "opencv": ("k1", "k2", "p1", "p2")}
"""Distortion coefficients each model may hold non-zero."""
UNDISTORT_ITERATIONS = 20
"""Most Newton steps inverting the distortion; converges to ~1e-12 well inside the image for |k1| < 0.5."""
UNDISTORT_TOLERANCE = 1e-14
"""Newton stops when no point moves more than this (normalized coordinates, ~1): the next step would be
~1e-28, below rounding."""
MIN_DEPTH = 1e-12
"""Depths closer to zero than this are clamped (a point on the camera plane projects far away)."""


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera model; fields are floats, or (N,) arrays for one camera per point."""

    model: CameraModel
    fx: float | np.ndarray
    fy: float | np.ndarray
    cx: float | np.ndarray
    cy: float | np.ndarray
    k1: float | np.ndarray = 0.0
    k2: float | np.ndarray = 0.0
    p1: float | np.ndarray = 0.0
    p2: float | np.ndarray = 0.0
    skew: float | np.ndarray = 0.0

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise ValueError(
                f"unknown camera model {self.model!r}; expected one of {', '.join(CAMERA_MODELS)}"
            )
        allowed = DISTORTION_PARAMETERS[self.model]
        for name in ("k1", "k2", "p1", "p2"):
            value = getattr(self, name)
            # Plain floats (the common case) are checked without numpy's per-call overhead.
            if name not in allowed and (value != 0 if isinstance(value, float) else np.any(value != 0)):
                raise ValueError(f"camera model {self.model} has no {name} (got {getattr(self, name)})")

    @property
    def K(self) -> np.ndarray:
        """3x3 [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] of a single camera."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], float)

    @property
    def distortion(self) -> np.ndarray:
        """(k1, k2, p1, p2): OpenCV's distortion coefficients (cv2 order)."""
        return np.array([self.k1, self.k2, self.p1, self.p2], float)

    @staticmethod
    def from_K(K: np.ndarray, model: CameraModel = "pinhole", k1: float = 0.0, k2: float = 0.0,
               p1: float = 0.0, p2: float = 0.0) -> Camera:
        """Camera of a 3x3 K (skew kept) and distortion coefficients."""
        K = np.asarray(K, float)
        return Camera(model=model, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
                      cy=float(K[1, 2]), k1=k1, k2=k2, p1=p1, p2=p2, skew=float(K[0, 1]))

    def as_model(self, model: CameraModel) -> Camera:
        """The same intrinsics in `model`: coefficients `model` lacks are dropped; simple-radial and
        radial share one focal length (the mean of fx and fy)."""
        values = {name: getattr(self, name) if name in DISTORTION_PARAMETERS[model] else 0.0
                  for name in ("k1", "k2", "p1", "p2")}
        if "f" in COLMAP_PARAMETERS[model]:
            values["fx"] = values["fy"] = (self.fx + self.fy) / 2
        return replace(self, model=model, **values)

    def pinhole(self) -> Camera:
        """The distortion-free camera with the same K: it maps normalized to *ideal* pixels."""
        return replace(self, model="pinhole", k1=0.0, k2=0.0, p1=0.0, p2=0.0)

    def colmap_params(self) -> list[float]:
        """Parameters in COLMAP's order for this model, in the project's pixel convention."""
        values = {name: float(getattr(self, name))
                  for name in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}
        values["f"] = values["fx"]
        return [values[name] for name in COLMAP_PARAMETERS[self.model]]

    @staticmethod
    def from_colmap(colmap_model: str, params: Sequence[float]) -> Camera:
        """Camera of a COLMAP model name (e.g. SIMPLE_RADIAL) and its parameters in COLMAP's order."""
        models = {name: model for model, name in COLMAP_MODEL_NAMES.items()}
        if colmap_model not in models:
            raise ValueError(f"unsupported COLMAP camera model {colmap_model!r}; expected one of "
                             f"{', '.join(models)}")
        model = models[colmap_model]
        names = COLMAP_PARAMETERS[model]
        if len(params) != len(names):
            raise ValueError(
                f"{colmap_model} has {len(names)} parameters ({' '.join(names)}), got {len(params)}"
            )
        values = dict(zip(names, map(float, params), strict=True))
        if "f" in values:
            values["fx"] = values["fy"] = values.pop("f")
        return Camera(model=model, **values)

    def to_dict(self) -> dict:
        """JSON-ready {model, fx, fy, cx, cy, k1, k2, p1, p2} of a single camera."""
        return {"model": self.model, **{f.name: float(getattr(self, f.name)) for f in fields(self)
                                        if f.name not in ("model", "skew")}}

    @staticmethod
    def take(cameras: Sequence[Camera], index: np.ndarray) -> Camera:
        """One camera per element of `index` (fields become arrays): cameras[index[n]] for point n."""
        models = {camera.model for camera in cameras}
        if len(models) != 1:
            raise ValueError(f"cameras of different models cannot be stacked: {sorted(models)}")
        index = np.asarray(index, np.int64)
        names = [f.name for f in fields(Camera) if f.name != "model"]
        first = cameras[0]
        if all(camera is first for camera in cameras):
            # One camera object for every image (fixed intrinsics, the common case): filled, not gathered
            # from a per-image table (24 instead of 70 us a call with lego's 90 images).
            arrays = {name: np.full(index.shape, float(getattr(first, name))) for name in names}
        else:
            arrays = {name: np.array([float(getattr(c, name)) for c in cameras])[index] for name in names}
        return Camera(model=models.pop(), **arrays)


def observation_cameras(cameras: Sequence[Camera], index: np.ndarray) -> Camera:
    """The camera of each element of `index`: the one Camera object itself when every camera is that object
    (its scalar fields broadcast: the same values, no per-element arrays to fill), else `Camera.take`."""
    first = cameras[0]
    return first if all(camera is first for camera in cameras) else Camera.take(cameras, index)


def as_camera(camera: Camera | np.ndarray) -> Camera:
    """A Camera as is; a 3x3 K as the pinhole camera it describes."""
    return camera if isinstance(camera, Camera) else Camera.from_K(camera)


CameraInput = Camera | np.ndarray | Sequence[Camera]
"""A 3x3 K (pinhole) or Camera shared by every image, or a sequence of Cameras, one per image."""


def is_shared(camera: CameraInput) -> bool:
    """True for one camera (a Camera or a 3x3 K), False for a sequence of per-image Cameras."""
    return isinstance(camera, Camera) or (isinstance(camera, np.ndarray) and camera.ndim == 2)


class Projection(NamedTuple):
    """Pixels of projected points and their depth along the optical axis (negative: behind)."""

    uv: np.ndarray       # (N, 2)
    depth: np.ndarray    # (N,)


class DistortedCoordinates(NamedTuple):
    """distort's x_d, y_d of coordinates x, y, with the r^2 and radial factor they came from."""

    x: np.ndarray
    y: np.ndarray
    r2: np.ndarray
    radial: np.ndarray


def distorted_coordinates(camera: Camera, x: np.ndarray, y: np.ndarray) -> DistortedCoordinates:
    """x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2), y_d = y (1 + k1 r^2 + k2 r^4) +
    p1 (r^2 + 2 y^2) + 2 p2 x y."""
    r2 = x * x + y * y
    radial = 1.0 + camera.k1 * r2 + camera.k2 * r2 * r2
    xy = x * y
    return DistortedCoordinates(x * radial + 2 * camera.p1 * xy + camera.p2 * (r2 + 2 * x * x),
                                y * radial + camera.p1 * (r2 + 2 * y * y) + 2 * camera.p2 * xy, r2, radial)


def distort(camera: Camera, x: np.ndarray) -> np.ndarray:
    """x_d = x (1 + k1 r^2 + k2 r^4) + [2 p1 x y + p2 (r^2 + 2 x^2), p1 (r^2 + 2 y^2) + 2 p2 x y], (N, 2)."""
    if camera.model == "pinhole":          # no coefficients: x_d = x
        return x
    distorted = distorted_coordinates(camera, x[..., 0], x[..., 1])
    return np.stack([distorted.x, distorted.y], axis=-1)


def undistort(camera: Camera, x_distorted: np.ndarray, iterations: int = UNDISTORT_ITERATIONS) -> np.ndarray:
    """x with distort(x) = x_d, by Newton's method from x = x_d (vectorized), (N, 2); it stops once every
    step is below UNDISTORT_TOLERANCE."""
    x_distorted = np.asarray(x_distorted, float)
    if camera.model == "pinhole":
        return x_distorted.copy()
    k1, k2, p1, p2 = camera.k1, camera.k2, camera.p1, camera.p2
    target_x, target_y = x_distorted[..., 0], x_distorted[..., 1]
    x, y = target_x.copy(), target_y.copy()
    # The step J^-1 (distort(x) - x_d) with the 2 x 2 Jacobian J = [[a, b], [b, d]] inverted in closed form,
    # distortion and Jacobian from one evaluation of r^2: np.linalg.solve on (N, 2, 2) stacks and twenty
    # fixed steps took 4.8 of an uncalibrated lego run's 12 s (107 calls on ~20,000 observations).
    for _ in range(iterations):
        distorted = distorted_coordinates(camera, x, y)
        residual_x, residual_y = distorted.x - target_x, distorted.y - target_y
        r2, radial = distorted.r2, distorted.radial
        d_radial = 2 * k1 + 4 * k2 * r2          # d radial / d(x or y) = d_radial * (x or y)
        a = radial + d_radial * x * x + 2 * p1 * y + 6 * p2 * x
        b = d_radial * x * y + 2 * p1 * x + 2 * p2 * y
        d = radial + d_radial * y * y + 6 * p1 * y + 2 * p2 * x
        with np.errstate(divide="ignore", invalid="ignore"):      # a singular J leaves that point NaN
            inverse_det = 1.0 / (a * d - b * b)
        step_x = (d * residual_x - b * residual_y) * inverse_det
        step_y = (a * residual_y - b * residual_x) * inverse_det
        x -= step_x
        y -= step_y
        if np.abs(step_x).max(initial=0.0) <= UNDISTORT_TOLERANCE and np.abs(step_y).max(
                initial=0.0) <= UNDISTORT_TOLERANCE:
            break
    return np.stack([x, y], axis=-1)


def normalized_to_pixel(camera: Camera, x: np.ndarray) -> np.ndarray:
    """u = fx x_d + skew y_d + cx, v = fy y_d + cy with x_d = distort(x), (N, 2)."""
    xd = distort(camera, np.asarray(x, float))
    return np.stack([camera.fx * xd[..., 0] + camera.skew * xd[..., 1] + camera.cx,
                     camera.fy * xd[..., 1] + camera.cy], axis=-1)


def pixel_to_normalized(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """x = undistort(K^-1 [u, v, 1]): the ray direction (x, y, 1) of each pixel, (N, 2)."""
    uv = np.asarray(uv, float)
    yd = (uv[..., 1] - camera.cy) / camera.fy
    xd = (uv[..., 0] - camera.cx - camera.skew * yd) / camera.fx
    return undistort(camera, np.stack([xd, yd], axis=-1))


def transfer_pixels(source: Camera, target: Camera, uv: np.ndarray) -> np.ndarray:
    """The pixels where `target` sees the rays that `source` sees at uv (same pose), (N, 2)."""
    return normalized_to_pixel(target, pixel_to_normalized(source, uv))


def ideal_pixels(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """The pixels the distortion-free camera with the same K would have seen: K pixel_to_normalized(uv)."""
    if camera.model == "pinhole":
        return np.asarray(uv, float)
    return transfer_pixels(camera, camera.pinhole(), uv)


def project(camera: Camera | np.ndarray, R: np.ndarray, t: np.ndarray, points: np.ndarray) -> Projection:
    """uv = normalized_to_pixel(x_cam[:2] / x_cam[2]), x_cam = R X + t.

    R is (3, 3) or (N, 3, 3), t (3,) or (N, 3), points (N, 3)."""
    camera = as_camera(camera)
    R, t, points = np.asarray(R, float), np.asarray(t, float), np.asarray(points, float)
    x_cam = (np.einsum("nij,nj->ni", R, points) if R.ndim == 3 else points @ R.T) + t
    depth = x_cam[..., 2]
    safe = np.where(np.abs(depth) < MIN_DEPTH, MIN_DEPTH, depth)
    # Each coordinate divided on its own: the (N, 2) / (N, 1) broadcast cost up to 6 times as much.
    normalized = np.empty(depth.shape + (2,))
    np.divide(x_cam[..., 0], safe, out=normalized[..., 0])
    np.divide(x_cam[..., 1], safe, out=normalized[..., 1])
    return Projection(uv=normalized_to_pixel(camera, normalized), depth=depth)


class Observations(NamedTuple):
    """Flat observations of points by posed cameras (world-to-camera R, t per observation)."""

    R: np.ndarray             # (O, 3, 3)
    t: np.ndarray             # (O, 3)
    uv: np.ndarray            # (O, 2) pixels
    point_index: np.ndarray   # (O,) int in [0, num_points)
    num_points: int


def reprojection_residuals(camera: Camera | np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """r_o = pi(camera, R_o X_p(o) + t_o) - uv_o, (O, 2) pixels, for flat `Observations` (R, t, uv,
    point_index); a 3x3 K is the pinhole camera. Depth is clamped, so behind-camera residuals are large."""
    return project(camera, obs.R, obs.t, np.asarray(points, float).take(obs.point_index, axis=0)).uv - obs.uv


def reprojection_errors(camera: Camera | np.ndarray, obs: Observations, points: np.ndarray) -> np.ndarray:
    """||r_o|| = ||pi(camera, R_o X_p(o) + t_o) - uv_o|| in pixels, inf where the point is behind the
    observing camera or not finite, (O,); a 3x3 K is the pinhole camera."""
    projection = project(camera, obs.R, obs.t, np.asarray(points, float).take(obs.point_index, axis=0))
    residuals = projection.uv - obs.uv
    error = np.sqrt(np.einsum("oi,oi->o", residuals, residuals))   # the norm's own sum, in fewer calls
    return np.where((projection.depth > 0) & np.isfinite(error), error, np.inf)
