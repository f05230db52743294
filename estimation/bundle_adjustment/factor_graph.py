"""Bundle adjustment with GTSAM: cameras and points that best explain the observed pixels.

Solves  argmin_{R_c, t_c, X_p}  sum_o huber_k( || pi(K (R_c X_p + t_c)) - uv_o || / sigma )
with huber_k(x) = x^2 / 2 for |x| <= k, k |x| - k^2 / 2 beyond (k = huber_threshold_px / sigma), as a
GTSAM NonlinearFactorGraph of GenericProjectionFactorCal3_S2 factors solved by Levenberg-Marquardt.
The gauge (7 DoF: rotation, translation, scale) is fixed by near-hard priors: a PriorFactorPose3 on each
fixed camera and, when only one camera is fixed, a RangeFactorPose3 holding the distance between the
centres of the first fixed camera and the scale-reference camera at its initial value.

Keys are plain integers (camera c -> c, point p -> num_cameras + p), not gtsam Symbols: the vectorized
gtsam.utilities.insertProjectionFactors takes the point keys as a float64 vector, which holds integers
exactly only below 2^53 (Symbol keys carry their character in the top byte).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from estimation.config import BundleAdjustmentConfig
from estimation.errors import InputError
from estimation.geometry.triangulation import Observations
from estimation.geometry.triangulation import reprojection_residuals as observation_residuals
from estimation.types import CameraPose

_LINEAR_SOLVERS = {
    "multifrontal_cholesky": "MULTIFRONTAL_CHOLESKY",
    "multifrontal_qr": "MULTIFRONTAL_QR",
    "sequential_cholesky": "SEQUENTIAL_CHOLESKY",
    "sequential_qr": "SEQUENTIAL_QR",
    "pcg_block_jacobi": "ITERATIVE",
}
_ORDERING_TYPES = {"colamd": "COLAMD", "metis": "METIS", "natural": "NATURAL"}


@dataclass(frozen=True)
class BundleAdjustmentResult:
    """Adjusted cameras and points with the reprojection error before and after."""

    poses: list[CameraPose]  # world-to-camera, same order as the input
    points: np.ndarray  # (N, 3); points without observations are returned unchanged
    initial_rms_px: float  # RMS over all observations (outliers included) of the pixel residual norm
    final_rms_px: float
    iterations: int  # Levenberg-Marquardt iterations
    seconds: float  # wall time of the whole call (graph construction included)
    initial_cost: float  # robust cost sum_o huber_k(||r_o|| / sigma), priors excluded
    final_cost: float


def camera_pose_to_gtsam(pose: CameraPose) -> gtsam.Pose3:
    """World-to-camera (R, t) -> GTSAM's pose of the camera in the world (camera-to-world): (R^T, C)."""
    return gtsam.Pose3(gtsam.Rot3(pose.R.T), pose.center)


def camera_pose_from_gtsam(pose: gtsam.Pose3) -> CameraPose:
    """GTSAM camera-to-world Pose3 (R_wc, C) -> world-to-camera (R = R_wc^T, t = -R C)."""
    return CameraPose.from_center(pose.rotation().matrix().T, pose.translation())


def reprojection_residuals(
    K: np.ndarray,
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
) -> np.ndarray:
    """r_o = pi(K (R_c X_p + t_c)) - uv_o for every observation, (O, 2) pixels."""
    rotations = np.stack([pose.R for pose in poses])
    translations = np.stack([pose.t for pose in poses])
    observations = Observations(
        R=rotations[camera_index], t=translations[camera_index], uv=uv,
        point_index=point_index, num_points=len(points),
    )
    return observation_residuals(K, observations, points)


def huber_cost(residuals: np.ndarray, huber_threshold_px: float, sigma_px: float = 1.0) -> float:
    """sum_o huber_k(|r_o| / sigma); huber_k(x) = x^2/2 if x <= k else k x - k^2/2; k = threshold / sigma."""
    x = np.linalg.norm(residuals, axis=1) / sigma_px
    k = huber_threshold_px / sigma_px
    return float(np.where(x <= k, 0.5 * x**2, k * x - 0.5 * k**2).sum())


def rms(residuals: np.ndarray) -> float:
    """sqrt(mean_o ||r_o||^2)."""
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1)))) if len(residuals) else 0.0


def _validate(
    K: np.ndarray,
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    fixed_cameras: Sequence[int],
    scale_reference: int | None,
) -> None:
    """Raise InputError naming the argument that does not fit the others."""
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"bundle_adjust: K must be a finite 3x3 matrix, got shape {K.shape}")
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


def _projection_factors(
    K: np.ndarray,
    num_cameras: int,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    config: BundleAdjustmentConfig,
) -> gtsam.NonlinearFactorGraph:
    """One GenericProjectionFactorCal3_S2 per observation, Huber-robust, keys camera c and point N_c + p."""
    graph = gtsam.NonlinearFactorGraph()
    calibration = gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])
    pixel_noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.huber_threshold_px / config.measurement_sigma_px),
        gtsam.noiseModel.Isotropic.Sigma(2, config.measurement_sigma_px),
    )
    # One vectorized call per camera instead of one Python call per observation.
    by_camera = np.argsort(camera_index, kind="stable")
    bounds = np.searchsorted(camera_index[by_camera], np.arange(num_cameras + 1))
    point_keys = (num_cameras + point_index[by_camera]).astype(float)
    measurements = np.ascontiguousarray(uv[by_camera].T)
    for camera in np.flatnonzero(np.diff(bounds)).tolist():
        begin, end = bounds[camera], bounds[camera + 1]
        gtsam.utilities.insertProjectionFactors(
            graph, camera, point_keys[begin:end], measurements[:, begin:end], pixel_noise, calibration
        )
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
    config: BundleAdjustmentConfig, camera_keys: np.ndarray, point_keys: np.ndarray
) -> gtsam.Ordering | None:
    """points_first: every point, then every camera (Schur complement order); None: let GTSAM choose."""
    if config.ordering != "points_first":
        return None
    ordering = gtsam.Ordering()
    for key in (*point_keys.tolist(), *camera_keys.tolist()):
        ordering.push_back(key)
    return ordering


IterationHook = Callable[[int, float], None]
"""Called after each Levenberg-Marquardt iteration with (iterations done, GTSAM's graph error after it)."""


def _optimizer_params(
    config: BundleAdjustmentConfig, ordering: gtsam.Ordering | None, on_iteration: IterationHook | None
) -> gtsam.LevenbergMarquardtParams:
    params = gtsam.LevenbergMarquardtParams()
    if on_iteration is not None:
        params.iterationHook = lambda iteration, _error_before, error_after: on_iteration(
            int(iteration), float(error_after)
        )
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(config.relative_error_tol)
    params.setAbsoluteErrorTol(config.absolute_error_tol)
    params.setlambdaInitial(config.lambda_initial)
    params.setlambdaFactor(config.lambda_factor)
    params.setDiagonalDamping(config.diagonal_damping)
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


def bundle_adjust(
    K: np.ndarray,
    poses: Sequence[CameraPose],
    points: np.ndarray,
    camera_index: np.ndarray,
    point_index: np.ndarray,
    uv: np.ndarray,
    config: BundleAdjustmentConfig,
    fixed_cameras: Sequence[int] = (0,),
    scale_reference: int | None = 1,
    on_iteration: IterationHook | None = None,
) -> BundleAdjustmentResult:
    """Minimize the Huber-robust reprojection error over all observed cameras and points (GTSAM LM).

    Observation o says camera `camera_index[o]` sees point `point_index[o]` at pixel `uv[o]`.
    `fixed_cameras` keep their pose (near-hard prior); with fewer than two of them, the distance between
    the centres of `fixed_cameras[0]` and `scale_reference` keeps its initial value (None: scale free).
    Cameras and points without observations (and not fixed) are returned unchanged.
    `on_iteration(iterations_done, graph_error)` is called after every LM iteration (progress, traces);
    graph_error is GTSAM's objective: the robust cost plus the (near-zero) gauge priors.
    """
    start = time.perf_counter()
    K = np.asarray(K, float)
    points = np.asarray(points, float)
    camera_index = np.asarray(camera_index, np.int64)
    point_index = np.asarray(point_index, np.int64)
    uv = np.asarray(uv, float)
    fixed_cameras = [int(c) for c in fixed_cameras]
    _validate(K, poses, points, camera_index, point_index, uv, fixed_cameras, scale_reference)
    use_scale_prior = len(fixed_cameras) < 2 and scale_reference is not None

    num_cameras = len(poses)
    extra_cameras = [*fixed_cameras, *([scale_reference] if use_scale_prior else [])]
    camera_keys = np.unique(np.concatenate([camera_index, extra_cameras]).astype(np.int64))
    observed_points = np.unique(point_index)
    point_keys = num_cameras + observed_points

    graph = _projection_factors(K, num_cameras, camera_index, point_index, uv, config)
    gtsam_poses = {camera: camera_pose_to_gtsam(poses[camera]) for camera in camera_keys.tolist()}
    graph.push_back(
        _gauge_factors(gtsam_poses, fixed_cameras, scale_reference if use_scale_prior else None, config)
    )
    initial = gtsam.Values()
    for camera, pose in gtsam_poses.items():
        initial.insert(camera, pose)
    for key, point in zip(point_keys.tolist(), points[observed_points], strict=True):
        initial.insert(key, point)

    params = _optimizer_params(config, _elimination_ordering(config, camera_keys, point_keys), on_iteration)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = optimizer.optimize()

    adjusted_poses = list(poses)
    for camera in camera_keys.tolist():
        adjusted_poses[camera] = camera_pose_from_gtsam(values.atPose3(camera))
    adjusted_points = points.copy()
    if len(observed_points):
        # extractPoint3 returns every Point3 in key order, i.e. in observed_points order.
        adjusted_points[observed_points] = gtsam.utilities.extractPoint3(values)

    initial_residuals = reprojection_residuals(K, poses, points, camera_index, point_index, uv)
    final_residuals = reprojection_residuals(
        K, adjusted_poses, adjusted_points, camera_index, point_index, uv
    )
    return BundleAdjustmentResult(
        poses=adjusted_poses,
        points=adjusted_points,
        initial_rms_px=rms(initial_residuals),
        final_rms_px=rms(final_residuals),
        iterations=int(optimizer.iterations()),
        seconds=time.perf_counter() - start,
        initial_cost=huber_cost(initial_residuals, config.huber_threshold_px, config.measurement_sigma_px),
        final_cost=huber_cost(final_residuals, config.huber_threshold_px, config.measurement_sigma_px),
    )
