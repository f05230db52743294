"""Bundle adjustment with GTSAM: cameras, points and (on request) intrinsics that best explain the pixels.

Solves  argmin_{R_c, t_c, X_p[, intrinsics]}  sum_o huber_k( ||pi(camera_c, R_c X_p + t_c) - uv_o|| / s_o )
with huber_k(x) = x^2 / 2 for |x| <= k, k |x| - k^2 / 2 beyond (k = huber_threshold_px / sigma), s_o =
sigma (measurement_sigma_px) times the observation's relative std-dev (1 unless given), as a
GTSAM NonlinearFactorGraph solved by Levenberg-Marquardt, or by Gauss-Newton falling back to it when a
step raises the cost (`BundleAdjustmentConfig.optimizer`); pi is `geometry.projection`'s camera model.
- Intrinsics fixed: the observations are first mapped to the ideal pixels of each camera's pinhole K
  (`projection.ideal_pixels`, exact for pinhole cameras; for distorted ones the residual is measured
  in the undistorted image) and each becomes a GenericProjectionFactorCal3_S2 (vectorized insertion).
- Intrinsics refined (`IntrinsicsRefinement`): each observation is a GeneralSFMFactor2 on (pose, point,
  calibration), the calibration a variable of the graph, one shared by every camera or one per camera:
  Cal3Bundler (f, k1, k2) for simple-radial and radial with the principal point held, Cal3DS2 (fx, fy,
  s, u0, v0, k1, k2, p1, p2) otherwise (Cal3Bundler has no principal point among its variables). What
  the model or the request holds fixed (the skew always, the principal point unless asked, as COLMAP
  does by default, the coefficients the model lacks) is held by a near-hard prior on that component
  only; a model with one focal length on a Cal3DS2 ties fx to fy by a near-hard factor on fx - fy.
The gauge (7 DoF: rotation, translation, scale) is fixed by near-hard priors: a PriorFactorPose3 on each
fixed camera and, when only one camera is fixed, a RangeFactorPose3 holding the distance between the
centres of the first fixed camera and the scale-reference camera at its initial value. With fixed
intrinsics the fixed cameras (but the range factor's anchor) are constants instead of variables: each of
their observations is a TriangulationFactorCal3_S2 on its point alone, so a local BA's many fixed
neighbours do not enlarge the reduced camera system (COLMAP holds them constant the same way).

Keys are plain integers (camera c -> c, point p -> num_cameras + p), not gtsam Symbols: the vectorized
gtsam.utilities.insertProjectionFactors takes the point keys as a float64 vector, which holds integers
exactly only below 2^53 (Symbol keys carry their character in the top byte). Calibration c has key
num_cameras + num_points + c.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import gtsam
import numpy as np
from scipy import sparse

from estimation.config import BundleAdjustmentConfig
from estimation.errors import InputError
from estimation.geometry.projection import (
    DISTORTION_PARAMETERS,
    Camera,
    CameraInput,
    as_camera,
    ideal_pixels,
    is_shared,
    observation_cameras,
)
from estimation.geometry.projection import reprojection_residuals as observation_residuals
from estimation.geometry.triangulation import Observations
from estimation.types import CameraPose

_LINEAR_SOLVERS = {
    "multifrontal_cholesky": "MULTIFRONTAL_CHOLESKY",
    "multifrontal_qr": "MULTIFRONTAL_QR",
    "sequential_cholesky": "SEQUENTIAL_CHOLESKY",
    "sequential_qr": "SEQUENTIAL_QR",
    "pcg_block_jacobi": "ITERATIVE",
}
POINT_COVARIANCE_CHUNK = 4096
"""Points whose camera-uncertainty term is formed at once (bounds a dense (3 chunk, cameras x 6) array)."""
_ORDERING_TYPES = {"colamd": "COLAMD", "metis": "METIS", "natural": "NATURAL"}
EQUAL_FOCALS_SIGMA_PX = 1e-3
"""Std-dev of fx - fy for a one-focal model on a Cal3DS2. Not fixed_intrinsics_sigma (1e-6): this factor
couples two variables, and at a precision of 1e12 the elimination loses the sum fx + fy to cancellation
(measured: Levenberg-Marquardt made no step at 1e-6 and the same steps at 1e-3 and 1e-1)."""


@dataclass(frozen=True)
class IntrinsicsRefinement:
    """Which intrinsics the BA refines; the skew always stays as given."""

    focal: bool = False            # fx, fy (f for simple-radial and radial)
    distortion: bool = False       # the coefficients the camera model has (none for pinhole)
    per_image: bool = False        # one calibration variable per camera instead of one shared by all
    principal_point: bool = False  # cx, cy

    def refines(self, model: str) -> bool:
        return self.focal or self.principal_point or (self.distortion and model != "pinhole")


class IntrinsicsCovariance(NamedTuple):
    """Marginal covariance of a shared camera's refined intrinsics at the optimum (how well the views
    determine them), for the pixel noise it was computed with."""

    names: tuple[str, ...]  # the refined components ("f" or "fx", "fy", "cx", "cy", "k1", ...)
    matrix: np.ndarray      # (k, k) in their units (pixels, unitless)

    def scaled(self, noise_ratio: float) -> IntrinsicsCovariance:
        """For noise_ratio times the pixel noise (the covariance grows with its square)."""
        return self._replace(matrix=self.matrix * noise_ratio**2)

    def sigma(self) -> dict[str, float]:
        """1-sigma of each component."""
        return {name: float(np.sqrt(v)) for name, v in zip(self.names, np.diag(self.matrix), strict=True)}

    def block(self, names: Sequence[str]) -> np.ndarray:
        """The covariance of the named components."""
        index = [self.names.index(name) for name in names]
        return self.matrix[np.ix_(index, index)]


class _ErrorInputs(NamedTuple):
    """What the reprojection residuals before a BA and after it (with the result's poses and points) are
    computed from, when first read."""

    initial_observed: Camera  # the camera of each observation (`observation_cameras`), before and after
    final_observed: Camera
    initial_poses: list[CameraPose]
    initial_points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    uv: np.ndarray
    config: BundleAdjustmentConfig  # its huber_threshold_px and measurement_sigma_px
    relative_sigma: np.ndarray | None  # (O,) each observation's std-dev / measurement_sigma_px (None: 1)


@dataclass(frozen=True)
class BundleAdjustmentResult:
    """Adjusted cameras and points; the reprojection error before and after is computed when first read
    (the mapper's local BAs never read it)."""

    poses: list[CameraPose]  # world-to-camera, same order as the input
    points: np.ndarray  # (N, 3); points without observations are returned unchanged
    iterations: int  # of the optimizer run that gave the result (a failed Gauss-Newton's not counted)
    seconds: float  # wall time of the adjustment (graph construction included, the error figures not)
    cameras: list[Camera]  # intrinsics per pose after the adjustment (the same object when shared)
    error_inputs: _ErrorInputs = field(repr=False, compare=False)
    # of a shared refined camera, for measurement_sigma_px pixel noise; None unless asked for
    intrinsics_covariance: IntrinsicsCovariance | None = None
    # (N, 3, 3) marginal covariance of each point for measurement_sigma_px pixel noise, conditioned on the
    # intrinsics (NaN for points without observations); None unless asked for
    point_covariances: np.ndarray | None = None

    @property
    def measured_pixel_sigma(self) -> float:
        """Per-axis pixel noise of the observations at the optimum: sqrt(sum ||r||^2 / (2 O - n)), n the
        number of free parameters (6 per variable camera, 3 per point, minus the 7 of the gauge)."""
        r = self.error_inputs
        free = 6 * len(np.unique(r.camera_index)) + 3 * len(np.unique(r.point_index)) - 7
        return float(np.sqrt(np.sum(self.final_residuals**2) / max(2 * len(r.uv) - free, 1)))

    @cached_property
    def initial_residuals(self) -> np.ndarray:
        """(O, 2) pixels at the input cameras, poses and points."""
        r = self.error_inputs
        return _observed_residuals(r.initial_observed, r.initial_poses, r.initial_points, r.camera_index,
                                   r.point_index, r.uv)

    @cached_property
    def final_residuals(self) -> np.ndarray:
        """(O, 2) pixels at the adjusted cameras, poses and points."""
        r = self.error_inputs
        return _observed_residuals(r.final_observed, self.poses, self.points, r.camera_index, r.point_index,
                                   r.uv)

    @property
    def initial_rms_px(self) -> float:
        """RMS over all observations (outliers included) of the pixel residual norm."""
        return rms(self.initial_residuals)

    @property
    def final_rms_px(self) -> float:
        """The same after the adjustment."""
        return rms(self.final_residuals)

    @property
    def initial_cost(self) -> float:
        """Robust cost sum_o huber_k(||r_o|| / sigma_o), priors excluded."""
        return self._cost(self.initial_residuals)

    @property
    def final_cost(self) -> float:
        """The same after the adjustment."""
        return self._cost(self.final_residuals)

    def _cost(self, residuals: np.ndarray) -> float:
        inputs = self.error_inputs
        if inputs.relative_sigma is not None:
            residuals = residuals / inputs.relative_sigma[:, None]   # the whitened residual the loss sees
        return huber_cost(residuals, inputs.config.huber_threshold_px, inputs.config.measurement_sigma_px)


def along_ray_sigmas(points: np.ndarray, centres: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """sigma_o = sqrt(r_o^T Sigma_o r_o), r_o = (X_o - C_o) / ||X_o - C_o||: each point's std-dev along its
    ray from a camera centre; points, centres (O, 3), covariances (O, 3, 3) -> (O,)."""
    rays = np.asarray(points, float) - np.asarray(centres, float)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return np.sqrt(np.einsum("oi,oij,oj->o", rays, covariances, rays))


def camera_pose_to_gtsam(pose: CameraPose) -> gtsam.Pose3:
    """World-to-camera (R, t) -> GTSAM's pose of the camera in the world (camera-to-world): (R^T, C)."""
    return gtsam.Pose3(gtsam.Rot3(pose.R.T), pose.center)


def camera_pose_from_gtsam(pose: gtsam.Pose3) -> CameraPose:
    """GTSAM camera-to-world Pose3 (R_wc, C) -> world-to-camera (R = R_wc^T, t = -R C)."""
    return CameraPose.from_center(pose.rotation().matrix().T, pose.translation())


def per_pose_cameras(camera: CameraInput, num_poses: int) -> list[Camera]:
    """One Camera per pose: a shared K or Camera repeated, or the given sequence as a list."""
    if is_shared(camera):
        return [as_camera(camera)] * num_poses
    cameras = [as_camera(c) for c in camera]
    if len(cameras) != num_poses:
        raise InputError(
            f"bundle_adjust: got {len(cameras)} cameras for {num_poses} poses (need one per pose)"
        )
    return cameras


def reprojection_residuals(
    camera: CameraInput,
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
) -> np.ndarray:
    """r_o = pi(camera_c, R_c X_p + t_c) - uv_o for every observation, (O, 2) pixels."""
    observed = observation_cameras(per_pose_cameras(camera, len(poses)), camera_index)
    return _observed_residuals(observed, poses, points, camera_index, point_index, uv)


def _observed_residuals(
    observed: Camera, poses: Sequence[CameraPose], points: np.ndarray, camera_index: np.ndarray,
    point_index: np.ndarray, uv: np.ndarray,
) -> np.ndarray:
    """r_o = pi(observed_o, R_c X_p + t_c) - uv_o, observed_o the camera of observation o
    (`observation_cameras`)."""
    rotations = np.stack([pose.R for pose in poses])
    translations = np.stack([pose.t for pose in poses])
    observations = Observations(
        R=rotations.take(camera_index, axis=0), t=translations.take(camera_index, axis=0), uv=uv,
        point_index=point_index, num_points=len(points),
    )
    return observation_residuals(observed, observations, points)


def huber_cost(residuals: np.ndarray, huber_threshold_px: float, sigma_px: float = 1.0) -> float:
    """sum_o huber_k(|r_o| / sigma); huber_k(x) = x^2/2 if x <= k else k x - k^2/2; k = threshold / sigma."""
    x = np.linalg.norm(residuals, axis=1) / sigma_px
    k = huber_threshold_px / sigma_px
    return float(np.where(x <= k, 0.5 * x**2, k * x - 0.5 * k**2).sum())


def rms(residuals: np.ndarray) -> float:
    """sqrt(mean_o ||r_o||^2)."""
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(residuals) else 0.0


def _validate(
    cameras: Sequence[Camera],
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    fixed_cameras: Sequence[int],
    scale_reference: int | None,
) -> None:
    """Raise InputError naming the argument that does not fit the others."""
    for camera in {id(camera): camera for camera in cameras}.values():   # a shared camera once
        if not (np.all(np.isfinite(camera.K)) and np.all(np.isfinite(camera.distortion))):
            raise InputError(f"bundle_adjust: camera {cameras.index(camera)}'s intrinsics must be finite")
    if len({camera.model for camera in cameras}) > 1:
        raise InputError("bundle_adjust: every camera must have the same camera model")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"bundle_adjust: points must be (N, 3), got shape {points.shape}")
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(f"bundle_adjust: uv must be (O, 2), got shape {uv.shape}")
    if not (camera_index.shape == point_index.shape == (len(uv),)):
        raise InputError(
            f"bundle_adjust: camera_index {camera_index.shape}, point_index {point_index.shape} and "
            f"uv {uv.shape} must describe the same number of observations"
        )
    if len(uv) and (camera_index.min() < 0 or camera_index.max() >= len(poses)):
        raise InputError(
            f"bundle_adjust: camera_index must lie in [0, {len(poses)}) (there are that many poses)"
        )
    if len(uv) and (point_index.min() < 0 or point_index.max() >= len(points)):
        raise InputError(
            f"bundle_adjust: point_index must lie in [0, {len(points)}) (there are that many points)"
        )
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(uv))):
        raise InputError("bundle_adjust: points and uv must be finite (found NaN or inf)")
    if len(fixed_cameras) == 0:
        raise InputError("bundle_adjust: fixed_cameras must name at least one camera (it fixes the gauge)")
    for camera in [*fixed_cameras, *([] if scale_reference is None else [scale_reference])]:
        if not 0 <= camera < len(poses):
            raise InputError(
                f"bundle_adjust: camera {camera} (fixed or scale reference) is not in [0, {len(poses)})"
            )
    if len(fixed_cameras) < 2 and scale_reference is not None:
        if scale_reference == fixed_cameras[0]:
            raise InputError("bundle_adjust: scale_reference must differ from the fixed camera")
        if np.linalg.norm(poses[scale_reference].center - poses[fixed_cameras[0]].center) <= 0:
            raise InputError("bundle_adjust: the fixed and scale-reference cameras share a centre (no scale)")


def _marked(size: int, *indices: np.ndarray | Sequence[int]) -> np.ndarray:
    """(size,) bool, True at every index in `indices` (sorted unique ids by flatnonzero: no np.unique)."""
    marked = np.zeros(size, bool)
    for index in indices:
        marked[np.asarray(index, np.int64)] = True
    return marked


def _pixel_noise(config: BundleAdjustmentConfig, relative_sigma: float = 1.0) -> gtsam.noiseModel.Base:
    """Huber-robust isotropic pixel noise of std-dev relative_sigma x measurement_sigma_px (the Huber
    threshold acts on the whitened residual, so it scales alike)."""
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.huber_threshold_px / config.measurement_sigma_px),
        gtsam.noiseModel.Isotropic.Sigma(2, relative_sigma * config.measurement_sigma_px),
    )


SIGMA_LEVELS_PER_OCTAVE = 4
"""Relative std-devs are rounded to 2^(k / 4): one noise model per level, and the per-camera vectorized
factor insertion stays one call per camera and level (a 19 % step between levels: a weight, not a
measurement)."""


class NoiseLevels(NamedTuple):
    """The observations' relative std-devs as a few shared levels."""

    level: np.ndarray     # (O,) index into sigmas
    sigmas: np.ndarray    # (L,) relative std-dev of each level


def noise_levels(relative_sigma: np.ndarray | None, num_observations: int) -> NoiseLevels:
    """s_o rounded to 2^(round(L log2 s_o) / L), L = SIGMA_LEVELS_PER_OCTAVE; None: one level of 1."""
    if relative_sigma is None:
        return NoiseLevels(np.zeros(num_observations, np.int64), np.ones(1))
    relative_sigma = np.asarray(relative_sigma, float)
    valid = relative_sigma.shape == (num_observations,) and np.all(np.isfinite(relative_sigma))
    if not (valid and np.all(relative_sigma > 0)):
        raise InputError(f"bundle_adjust: relative_sigma must hold one positive finite std-dev per "
                         f"observation ({num_observations}), got shape {relative_sigma.shape}")
    exponents = np.round(np.log2(relative_sigma) * SIGMA_LEVELS_PER_OCTAVE)
    values, level = np.unique(exponents, return_inverse=True)
    return NoiseLevels(level.reshape(-1), 2.0 ** (values / SIGMA_LEVELS_PER_OCTAVE))


def _projection_factors(
    cameras: Sequence[Camera],
    camera_index: np.ndarray,
    point_index: np.ndarray,
    ideal: np.ndarray,
    config: BundleAdjustmentConfig,
    constant_poses: dict[int, gtsam.Pose3],
    levels: NoiseLevels,
) -> gtsam.NonlinearFactorGraph:
    """Fixed intrinsics: one GenericProjectionFactorCal3_S2 per observation on its ideal pixel
    (`projection.ideal_pixels`: K_c undistorted), Huber-robust at its noise level, keys camera c and point
    N_c + p; observations of a camera in `constant_poses` are TriangulationFactorCal3_S2 on the point
    alone (the pose is no variable)."""
    graph = gtsam.NonlinearFactorGraph()
    num_cameras, num_levels = len(cameras), len(levels.sigmas)
    noise = [_pixel_noise(config, sigma) for sigma in levels.sigmas.tolist()]
    # One vectorized call per variable camera (and noise level) instead of one Python call per observation.
    group_of = camera_index * num_levels + levels.level
    by_camera = np.argsort(group_of, kind="stable")
    bounds = np.searchsorted(group_of.take(by_camera), np.arange(num_cameras * num_levels + 1))
    keys = num_cameras + point_index.take(by_camera)
    point_keys, key_list = keys.astype(float), keys.tolist()
    rows = ideal.take(by_camera, axis=0)   # a contiguous pixel per factor converts faster
    measurements = np.ascontiguousarray(rows.T)
    calibrations: dict[int, gtsam.Cal3_S2] = {}   # by Camera object: a shared camera's is built once
    # Bound once: the per-observation loop below is the BA's largest Python cost (~1 us per factor).
    add, triangulation_factor = graph.add, gtsam.TriangulationFactorCal3_S2
    for group in np.flatnonzero(np.diff(bounds)).tolist():
        camera, pixel_noise = group // num_levels, noise[group % num_levels]
        begin, end = bounds[group], bounds[group + 1]
        calibration = calibrations.get(id(cameras[camera]))
        if calibration is None:
            calibration = calibrations[id(cameras[camera])] = _pinhole_calibration(cameras[camera])
        if camera in constant_poses:
            pinhole = gtsam.PinholeCameraCal3_S2(constant_poses[camera], calibration)
            for key, measured in zip(key_list[begin:end], rows[begin:end], strict=True):
                add(triangulation_factor(pinhole, measured, pixel_noise, key))
        else:
            gtsam.utilities.insertProjectionFactors(
                graph, camera, point_keys[begin:end], measurements[:, begin:end], pixel_noise, calibration
            )
    return graph


def _pinhole_calibration(camera: Camera) -> gtsam.Cal3_S2:
    """The GTSAM calibration of the camera's pinhole K (fx, fy, skew, cx, cy)."""
    return gtsam.Cal3_S2(camera.fx, camera.fy, camera.skew, camera.cx, camera.cy)


def _one_focal(model: str) -> bool:
    """simple-radial and radial have one focal length f = fx = fy."""
    return model in ("simple-radial", "radial")


def _uses_bundler(model: str, principal_point: bool = False) -> bool:
    """Cal3Bundler (one focal length, k1, k2; principal point a constant) for simple-radial and radial
    with the principal point held; Cal3DS2 otherwise."""
    return _one_focal(model) and not principal_point


def camera_to_gtsam(camera: Camera, principal_point: bool = False) -> gtsam.Cal3Bundler | gtsam.Cal3DS2:
    """The GTSAM calibration with the same projection as `camera` (a Cal3DS2 whenever the principal
    point is to be refined)."""
    if _uses_bundler(camera.model, principal_point):
        return gtsam.Cal3Bundler(camera.fx, camera.k1, camera.k2, camera.cx, camera.cy)
    return gtsam.Cal3DS2(camera.fx, camera.fy, camera.skew, camera.cx, camera.cy,
                         camera.k1, camera.k2, camera.p1, camera.p2)


def camera_from_gtsam(calibration: gtsam.Cal3Bundler | gtsam.Cal3DS2, like: Camera) -> Camera:
    """`like` (model, skew) with the focal lengths, principal point and coefficients of `calibration`
    (those the model lacks, held near zero by a prior, are set to exactly zero; a one-focal model's fx
    and fy, tied by a near-hard factor, become their mean)."""
    bundler = isinstance(calibration, gtsam.Cal3Bundler)
    coefficients = {"k1": calibration.k1(), "k2": calibration.k2(),
                    "p1": 0.0 if bundler else calibration.p1(), "p2": 0.0 if bundler else calibration.p2()}
    kept = {name: value for name, value in coefficients.items() if name in DISTORTION_PARAMETERS[like.model]}
    fx = calibration.fx()
    fy = fx if bundler else calibration.fy()
    if _one_focal(like.model):
        fx = fy = (fx + fy) / 2
    return Camera(like.model, fx=fx, fy=fy, cx=calibration.px(), cy=calibration.py(), skew=like.skew, **kept)


def _tangent_names(model: str, principal_point: bool) -> list[str]:
    """The camera parameter behind each component of the GTSAM calibration's tangent vector."""
    if _uses_bundler(model, principal_point):
        return ["f", "k1", "k2"]
    return ["fx", "fy", "skew", "cx", "cy", "k1", "k2", "p1", "p2"]


def _information(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, dim_of: Callable[[int], int]
                 ) -> tuple[sparse.csc_matrix, list[int], np.ndarray]:
    """H = J^T J (J: the whitened, robust-weighted Jacobian at `values`), its keys in column order and the
    tangent dimension of each (`dim_of(key)`)."""
    linear = graph.linearize(values)
    rows, cols, entries = linear.sparseJacobian_()
    keys = sorted(linear.keys())   # sparseJacobian_: columns in key order, 1-based (row, col, value)
    dims = np.array([dim_of(key) for key in keys])
    size = int(dims.sum())
    in_a = cols <= size   # the last column is the right-hand side b of [A | b]
    jacobian = sparse.csr_matrix(
        (entries[in_a], (rows[in_a].astype(np.int64) - 1, cols[in_a].astype(np.int64) - 1)),
        shape=(int(rows.max()), size))
    return (jacobian.T @ jacobian).tocsc(), keys, dims


def _point_block_inverses(information: sparse.csc_matrix, points: np.ndarray) -> np.ndarray:
    """(P, 3, 3): the pseudo-inverse of each point's 3x3 block of H (columns `points`, three per point)."""
    block_diagonal = information[points][:, points].tocoo()
    blocks = np.zeros((len(points) // 3, 3, 3))
    np.add.at(blocks, (block_diagonal.row // 3, block_diagonal.row % 3, block_diagonal.col % 3),
              block_diagonal.data)
    return np.linalg.pinv(blocks)


def _covariance_of(information: np.ndarray) -> np.ndarray:
    """information^-1 of a symmetric positive definite matrix, its pseudo-inverse where it is not (an
    indeterminate direction); the held gauge makes a model's camera block definite, where the inverse
    costs far less than the pseudo-inverse's SVD (lego's 540 x 540 block: `_point_covariances` 0.14 -> 0.10 s
    under `python -m cProfile benchmarks/bench_sfm.py --sets lego --no-pycolmap`)."""
    try:
        np.linalg.cholesky(information)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(information)
    return np.linalg.inv(information)


def _block_diagonal(blocks: np.ndarray) -> sparse.bsr_matrix:
    count = len(blocks)
    return sparse.bsr_matrix((blocks, np.arange(count), np.arange(count + 1)), shape=(3 * count, 3 * count))


def _intrinsics_covariance(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, calibration_key: int,
                           num_cameras: int, fixed_cameras: Sequence[int], model: str,
                           refine: IntrinsicsRefinement) -> IntrinsicsCovariance:
    """Marginal covariance of the refined components of the calibration: inv(S) with S the Schur
    complement of the points in H = J^T J (J: the whitened, robust-weighted Jacobian at the optimum),
    conditioned on what is held (the fixed cameras, the calibration's held components).

    Computed here rather than by gtsam.Marginals, whose Cholesky refuses the whole system when one
    point or the near-hard priors make it nearly indeterminate (measured on a synthetic object ring);
    each point's 3x3 block is pseudo-inverted instead."""
    calibration_dim = len(_tangent_names(model, refine.principal_point))
    information, keys, dims = _information(graph, values, lambda key: (
        6 if key < num_cameras else calibration_dim if key == calibration_key else 3))
    offsets = np.concatenate([[0], np.cumsum(dims)])
    is_point = np.repeat([num_cameras <= key != calibration_key for key in keys], dims)
    points, rest = np.flatnonzero(is_point), np.flatnonzero(~is_point)
    inverse = _block_diagonal(_point_block_inverses(information, points))
    coupling = information[rest][:, points]
    schur = information[rest][:, rest].toarray() - (coupling @ inverse @ coupling.T).toarray()
    # Condition on the held variables: drop their rows and columns.
    held = np.zeros(int(offsets[-1]), bool)
    for key, begin, dim in zip(keys, offsets[:-1], dims, strict=True):
        if key in fixed_cameras:
            held[begin:begin + dim] = True
        elif key == calibration_key:
            held[begin:begin + dim] = ~_free_components(model, refine)
    calibration = np.zeros(int(offsets[-1]), bool)
    calibration_begin = offsets[keys.index(calibration_key)]
    calibration[calibration_begin:calibration_begin + calibration_dim] = True
    kept = ~held[rest]
    covariance = np.linalg.inv(schur[np.ix_(kept, kept)])
    in_calibration = calibration[rest][kept]
    free = _free_components(model, refine)
    names = tuple(name for name, is_free in zip(_tangent_names(model, refine.principal_point), free,
                                                strict=True) if is_free)
    return IntrinsicsCovariance(names, covariance[np.ix_(in_calibration, in_calibration)])


def _point_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, num_cameras: int
                       ) -> np.ndarray:
    """(P, 3, 3) marginal covariance of each point variable (key order), the cameras marginalized out:
    Sigma_p = H_pp^-1 + H_pp^-1 H_pc S^-1 H_cp H_pp^-1, S = H_cc - H_cp H_pp^-1 H_pc (Schur complement).

    The same marginals gtsam.Marginals gives on a well-determined graph, computed block-wise like
    `_intrinsics_covariance` (one nearly indeterminate point does not refuse them all)."""
    information, keys, dims = _information(graph, values, lambda key: 6 if key < num_cameras else 3)
    is_point = np.repeat([key >= num_cameras for key in keys], dims)
    points, rest = np.flatnonzero(is_point), np.flatnonzero(~is_point)
    block_inverses = _point_block_inverses(information, points)
    if len(rest) == 0:
        return block_inverses
    coupling = information[points][:, rest].tocsr()   # H_pc, rows three per point
    reduced = coupling.T @ _block_diagonal(block_inverses) @ coupling
    camera_covariance = _covariance_of(information[rest][:, rest].toarray() - reduced.toarray())
    # Per point, lifted = H_pp^-1 H_pc is nonzero only in the columns of the cameras that see the point:
    # kept sparse, its product with S^-1 costs its non-zeros, not every camera column of every point.
    lifted = (_block_diagonal(block_inverses) @ coupling).tocsr()
    covariances = block_inverses.copy()
    for begin in range(0, len(block_inverses), POINT_COVARIANCE_CHUNK):
        end = min(begin + POINT_COVARIANCE_CHUNK, len(block_inverses))
        rows = lifted[3 * begin:3 * end]
        spread = rows @ camera_covariance   # dense (3 chunk, C): row 3p + i is lifted_p,i S^-1
        for i in range(3):
            for j in range(3):
                # sum_s spread[3p + i, s] lifted[3p + j, s]: entry (i, j) of lifted_p S^-1 lifted_p^T
                products = rows[j::3].multiply(spread[i::3])
                covariances[begin:end, i, j] += np.asarray(products.sum(axis=1)).ravel()
    return covariances


def _free_components(model: str, refine: IntrinsicsRefinement) -> np.ndarray:
    """Which components of the GTSAM calibration's tangent vector the BA may change."""
    distortion = refine.distortion and model != "pinhole"
    k2 = distortion and model in ("radial", "opencv")
    if _uses_bundler(model, refine.principal_point):   # (f, k1, k2)
        return np.array([refine.focal, distortion, k2])
    tangential = distortion and model == "opencv"       # fx fy s, u0 v0, k1 k2 p1 p2
    return np.array([refine.focal, refine.focal, False, refine.principal_point, refine.principal_point,
                     distortion, k2, tangential, tangential])


def _equal_focals_factor(key: int) -> gtsam.CustomFactor:
    """fx - fy = 0 on a Cal3DS2 variable (tangent order fx, fy, s, u0, v0, k1, k2, p1, p2), within
    EQUAL_FOCALS_SIGMA_PX."""
    jacobian = np.zeros((1, 9))
    jacobian[0, :2] = (1.0, -1.0)

    def error(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        calibration = values.atCal3DS2(factor.keys()[0])
        if jacobians is not None:
            jacobians[0] = jacobian
        return np.array([calibration.fx() - calibration.fy()])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, EQUAL_FOCALS_SIGMA_PX), [key], error)


def _calibrated_factors(
    cameras: Sequence[Camera],
    calibration_of_camera: np.ndarray,
    calibration_offset: int,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    refine: IntrinsicsRefinement,
    config: BundleAdjustmentConfig,
    levels: NoiseLevels,
) -> gtsam.NonlinearFactorGraph:
    """Refined intrinsics: a GeneralSFMFactor2 per observation on (pose c, point N_c + p, calibration
    key calibration_offset + calibration_of_camera[c]) at its noise level, and per calibration a prior
    holding exactly the components that `refine` and the model keep fixed."""
    graph = gtsam.NonlinearFactorGraph()
    model = cameras[0].model
    bundler = _uses_bundler(model, refine.principal_point)
    factor = gtsam.GeneralSFMFactor2Cal3Bundler if bundler else gtsam.GeneralSFMFactor2Cal3DS2
    prior = gtsam.PriorFactorCal3Bundler if bundler else gtsam.PriorFactorCal3DS2
    noise = [_pixel_noise(config, sigma) for sigma in levels.sigmas.tolist()]
    point_keys = len(cameras) + point_index
    observation_calibration = calibration_offset + calibration_of_camera[camera_index]
    for measured, level, pose_key, point_key, calibration_key in zip(
        uv, levels.level.tolist(), camera_index.tolist(), point_keys.tolist(),
        observation_calibration.tolist(), strict=True,
    ):
        graph.add(factor(measured, noise[level], pose_key, point_key, calibration_key))
    held = ~_free_components(model, refine)
    hold_noise = gtsam.noiseModel.Diagonal.Precisions(held / config.fixed_intrinsics_sigma**2)
    for key in np.unique(observation_calibration).tolist():
        first = int(np.flatnonzero(calibration_of_camera == key - calibration_offset)[0])
        graph.add(prior(key, camera_to_gtsam(cameras[first], refine.principal_point), hold_noise))
        if _one_focal(model) and not bundler:
            graph.add(_equal_focals_factor(key))
    return graph


def _gauge_factors(
    gtsam_poses: dict[int, gtsam.Pose3],
    fixed_cameras: Sequence[int],
    scale_reference: int | None,
    config: BundleAdjustmentConfig,
) -> gtsam.NonlinearFactorGraph:
    """Near-hard PriorFactorPose3 per fixed camera; RangeFactorPose3 holding |C_ref - C_fixed0| as it is."""
    graph = gtsam.NonlinearFactorGraph()
    prior_noise = gtsam.noiseModel.Isotropic.Sigma(6, config.fixed_camera_sigma)
    for camera in fixed_cameras:
        graph.add(gtsam.PriorFactorPose3(camera, gtsam_poses[camera], prior_noise))
    if scale_reference is not None:
        anchor = fixed_cameras[0]
        distance = float(
            np.linalg.norm(gtsam_poses[scale_reference].translation() - gtsam_poses[anchor].translation())
        )
        range_noise = gtsam.noiseModel.Isotropic.Sigma(1, config.scale_sigma_relative * distance)
        graph.add(gtsam.RangeFactorPose3(anchor, scale_reference, distance, range_noise))
    return graph


def _elimination_ordering(
    config: BundleAdjustmentConfig, camera_keys: np.ndarray, point_keys: np.ndarray,
    calibration_keys: np.ndarray,
) -> gtsam.Ordering | None:
    """points_first: every point, then every camera and calibration (Schur complement order);
    None: let GTSAM choose."""
    if config.ordering != "points_first":
        return None
    return gtsam.Ordering([*point_keys.tolist(), *camera_keys.tolist(), *calibration_keys.tolist()])


IterationHook = Callable[[int, float], None]
"""Called after each optimizer iteration with (iterations done, GTSAM's graph error after it)."""


def _optimizer_params(
    params: gtsam.NonlinearOptimizerParams, config: BundleAdjustmentConfig, ordering: gtsam.Ordering | None,
    on_iteration: Callable[[int, float, float], None],
) -> gtsam.NonlinearOptimizerParams:
    """`params` (of any GTSAM optimizer) with the stopping rule, linear solver and ordering of `config`;
    on_iteration(iteration, error before, error after) is GTSAM's iteration hook."""
    params.iterationHook = on_iteration
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(config.absolute_error_tol)
    params.setLinearSolverType(_LINEAR_SOLVERS[config.linear_solver])
    if config.linear_solver == "pcg_block_jacobi":
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        params.setIterativeParams(pcg)
    if ordering is None:
        params.setOrderingType(_ORDERING_TYPES[config.ordering])
    else:
        params.setOrdering(ordering)
    return params


def _levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, config: BundleAdjustmentConfig,
    ordering: gtsam.Ordering | None, on_iteration: IterationHook | None,
) -> tuple[gtsam.Values, int]:
    """GTSAM's Levenberg-Marquardt from `initial`: (values, iterations)."""
    def hook(iteration: int, _error_before: float, error_after: float) -> None:
        if on_iteration is not None:
            on_iteration(int(iteration), float(error_after))

    params = _optimizer_params(gtsam.LevenbergMarquardtParams(), config, ordering, hook)
    params.setlambdaInitial(config.lambda_initial)
    params.setlambdaFactor(config.lambda_factor)
    params.setDiagonalDamping(config.diagonal_damping)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    return optimizer.optimize(), int(optimizer.iterations())


def _gauss_newton(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, config: BundleAdjustmentConfig,
    ordering: gtsam.Ordering | None,
) -> tuple[gtsam.Values, list[tuple[int, float]]] | None:
    """GTSAM's Gauss-Newton from `initial`: (values, (iteration, error after) of each iteration); None
    when a step raised the cost (GTSAM's Gauss-Newton would return that step) or the undamped system was
    indeterminate."""
    trace: list[tuple[int, float, float]] = []
    params = _optimizer_params(gtsam.GaussNewtonParams(), config, ordering,
                               lambda *iteration: trace.append(iteration))
    try:
        values = gtsam.GaussNewtonOptimizer(graph, initial, params).optimize()
    except RuntimeError:   # IndeterminantLinearSystemException: LM's damping makes the system determinate
        return None
    if any(after > before for _, before, after in trace):
        return None
    return values, [(int(iteration), float(after)) for iteration, _, after in trace]


def _optimize(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, config: BundleAdjustmentConfig,
    ordering: gtsam.Ordering | None, on_iteration: IterationHook | None,
) -> tuple[gtsam.Values, int]:
    """config.optimizer from `initial`: (values, iterations of the run that gave them); Gauss-Newton
    falls back to Levenberg-Marquardt from `initial` when it fails (on_iteration then sees LM's only)."""
    if config.optimizer == "gauss_newton":
        result = _gauss_newton(graph, initial, config, ordering)
        if result is not None:
            values, trace = result
            for iteration, error in trace if on_iteration is not None else []:
                on_iteration(iteration, error)
            return values, len(trace)
    return _levenberg_marquardt(graph, initial, config, ordering, on_iteration)


def bundle_adjust(
    camera: CameraInput,
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    config: BundleAdjustmentConfig,
    fixed_cameras: Sequence[int] = (0,),
    scale_reference: int | None = 1,
    on_iteration: IterationHook | None = None,
    refine: IntrinsicsRefinement = IntrinsicsRefinement(),
    intrinsics_covariance: bool = False,
    point_covariances: bool = False,
    relative_sigma: np.ndarray | None = None,
) -> BundleAdjustmentResult:
    """Minimize the Huber-robust reprojection error over all observed cameras and points (config.optimizer).

    `camera` is a 3x3 K or Camera shared by every pose, or one Camera per pose. Observation o says
    camera `camera_index[o]` sees point `point_index[o]` at pixel `uv[o]`.
    `fixed_cameras` keep their pose (near-hard prior); with fewer than two of them, the distance between
    the centres of `fixed_cameras[0]` and `scale_reference` keeps its initial value (None: scale free).
    `refine` says which intrinsics are variables (shared by all cameras unless `refine.per_image`);
    the result's `cameras` carry them.
    Cameras and points without observations (and not fixed) are returned unchanged.
    `on_iteration(iterations_done, graph_error)` is called after every iteration (progress, traces);
    graph_error is GTSAM's objective: the robust cost plus the (near-zero) gauge priors.
    `intrinsics_covariance`: also the marginal covariance of a shared refined camera's intrinsics
    (how well the views determine them; one more elimination of the graph).
    `point_covariances`: also each point's marginal covariance (the cameras marginalized out, the
    intrinsics held; `_point_covariances`); refused with refined intrinsics.
    `relative_sigma` (O,) > 0: each observation's pixel std-dev as a multiple of measurement_sigma_px
    (e.g. from its keypoint's scale), rounded to `noise_levels`; None: every observation alike.
    """
    start = time.perf_counter()
    cameras = per_pose_cameras(camera, len(poses))
    points = np.asarray(points, float)
    camera_index = np.asarray(camera_index, np.int64)
    point_index = np.asarray(point_index, np.int64)
    uv = np.asarray(uv, float)
    fixed_cameras = [int(c) for c in fixed_cameras]
    _validate(cameras, poses, points, camera_index, point_index, uv, fixed_cameras, scale_reference)
    if point_covariances and refine.refines(cameras[0].model):
        raise InputError("point covariances are computed with the intrinsics held; refine none of them")
    use_scale_prior = len(fixed_cameras) < 2 and scale_reference is not None
    observed = observation_cameras(cameras, camera_index)   # the camera of each observation, read once

    num_cameras = len(poses)
    refines = refine.refines(cameras[0].model) and len(uv) > 0
    # With fixed intrinsics, fixed cameras are constants; the scale prior's anchor stays a variable.
    constant_cameras = set() if refines else set(fixed_cameras[1:] if use_scale_prior else fixed_cameras)
    extra_cameras = [*fixed_cameras, *([scale_reference] if use_scale_prior else [])]
    camera_keys = np.flatnonzero(_marked(num_cameras, camera_index, extra_cameras)
                                 & ~_marked(num_cameras, list(constant_cameras)))
    observed_points = np.flatnonzero(_marked(len(points), point_index))
    point_keys = num_cameras + observed_points
    # Calibration variable of each camera: its own, or the one they all share.
    calibration_of_camera = np.arange(num_cameras) if refine.per_image else np.zeros(num_cameras, np.int64)
    calibration_offset = num_cameras + len(points)
    calibration_keys = (calibration_offset + np.unique(calibration_of_camera[camera_index])
                        if refines else np.zeros(0, np.int64))

    levels = noise_levels(relative_sigma, len(uv))
    if refines:
        graph = _calibrated_factors(cameras, calibration_of_camera, calibration_offset, camera_index,
                                    point_index, uv, refine, config, levels)
    else:
        constant_poses = {c: camera_pose_to_gtsam(poses[c]) for c in constant_cameras}
        ideal = ideal_pixels(observed, uv) if len(uv) else uv
        graph = _projection_factors(cameras, camera_index, point_index, ideal, config, constant_poses, levels)
    gtsam_poses = {c: camera_pose_to_gtsam(poses[c]) for c in camera_keys.tolist()}
    graph.push_back(_gauge_factors(gtsam_poses, [c for c in fixed_cameras if c not in constant_cameras],
                                   scale_reference if use_scale_prior else None, config))
    initial = gtsam.Values()
    for c, pose in gtsam_poses.items():
        initial.insert(c, pose)
    insert_point = initial.insertPoint3   # bound once: one call per point
    for key, point in zip(point_keys.tolist(), points.take(observed_points, axis=0), strict=True):
        insert_point(key, point)
    for key in calibration_keys.tolist():
        first = int(np.flatnonzero(calibration_of_camera == key - calibration_offset)[0])
        initial.insert(key, camera_to_gtsam(cameras[first], refine.principal_point))

    ordering = _elimination_ordering(config, camera_keys, point_keys, calibration_keys)
    values, iterations = _optimize(graph, initial, config, ordering, on_iteration)

    adjusted_poses = list(poses)
    for c in camera_keys.tolist():
        adjusted_poses[c] = camera_pose_from_gtsam(values.atPose3(c))
    # extractPoint3 returns every Point3 in key order, i.e. in observed_points order.
    if len(observed_points) == len(points) > 0:   # every point observed (the mapper's case): no copy to fill
        adjusted_points = gtsam.utilities.extractPoint3(values)
    else:
        adjusted_points = points.copy()
        if len(observed_points):
            adjusted_points[observed_points] = gtsam.utilities.extractPoint3(values)
    adjusted_cameras = list(cameras)
    if refines:
        bundler = _uses_bundler(cameras[0].model, refine.principal_point)
        at = values.atCal3Bundler if bundler else values.atCal3DS2
        refined = {key - calibration_offset: camera_from_gtsam(at(key), cameras[0])
                   for key in calibration_keys.tolist()}
        adjusted_cameras = [refined.get(int(calibration_of_camera[c]), cameras[c])
                            for c in range(num_cameras)]
    covariance = None
    if refines and intrinsics_covariance and not refine.per_image:
        covariance = _intrinsics_covariance(graph, values, int(calibration_keys[0]), num_cameras,
                                            fixed_cameras, cameras[0].model, refine)

    marginals = None
    if point_covariances:
        marginals = np.full((len(points), 3, 3), np.nan)
        marginals[observed_points] = _point_covariances(graph, values, num_cameras)
    adjusted_observed = observation_cameras(adjusted_cameras, camera_index) if refines else observed
    # Copies of what the caller may change before reading the error figures.
    error_inputs = _ErrorInputs(observed, adjusted_observed, list(poses), points.copy(), camera_index.copy(),
                                point_index.copy(), uv.copy(), config,
                                None if relative_sigma is None else levels.sigmas[levels.level])
    return BundleAdjustmentResult(
        poses=adjusted_poses,
        points=adjusted_points,
        iterations=iterations,
        seconds=time.perf_counter() - start,
        cameras=adjusted_cameras,
        error_inputs=error_inputs,
        intrinsics_covariance=covariance,
        point_covariances=marginals,
    )
