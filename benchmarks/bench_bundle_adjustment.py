"""Bundle adjustment, one problem solved side by side by three solvers; prints a table.

- ours:  estimation.bundle_adjustment.factor_graph.bundle_adjust (GTSAM Levenberg-Marquardt), timed from
         the arrays (graph construction and result extraction included), once per --linear-solvers entry:
         by default the config's default (multifrontal Cholesky, points eliminated first) and pcg_block_jacobi
         (GTSAM's conjugate gradient, block-Jacobi preconditioner: inexact steps);
- ceres: Ceres through pyceres, with COLMAP's C++ reprojection cost (pycolmap.cost_functions,
         pycolmap 3.13: pose as quaternion + translation blocks), each of DENSE_SCHUR, SPARSE_SCHUR and
         ITERATIVE_SCHUR; the verdicts compare with the fastest of them. Its time is pyceres.solve's
         (the Python loop building the problem, one call per observation, is reported apart);
- scipy: scipy.optimize.least_squares, the usual hand-written route (as the SciPy cookbook's "Large-scale
         bundle adjustment"): rotation-vector cameras, vectorized residuals, finite-difference Jacobian
         with jac_sparsity, method="trf", x_scale="jac" (tr_solver lsmr).

All three minimize the same cost: sum_o huber_k(||r_o||) with k = huber_threshold_px on the 2-vector
residual of each observation (GTSAM's robust noise model and Ceres' HuberLoss both act on the
2-vector; scipy's loss="huber" would act on u and v separately, a different objective, so the scipy
residual function returns the 2-vector scaled to sqrt(2 huber_k(||r||)) and uses loss="linear").
The gauge is fixed the same way in all three: camera 0 held, and the scale held (ours: a range prior on
the distance to camera 1; ceres and scipy: one translation coordinate of camera 1 held). Final costs
are all evaluated by the same function (estimation.bundle_adjustment.factor_graph.huber_cost) on the
returned poses and points. Every solver runs on one thread (GTSAM as built here has no TBB; Ceres
num_threads=1; BLAS limited to one thread), so on a shared machine the process CPU seconds are the fairer
figure and the verdicts use them; wall seconds are printed beside them.

Two times per solver, side by side (the issue's target reads "ours reaches the same final cost as Ceres
(within 1 %) in at most 1.5x Ceres' time, and at least 5x faster than the scipy route brought to the
same final cost", which fits either):
(a) time to the solver's own convergence, all with the same stop: relative cost decrease below
    relative_error_tol (GTSAM relativeErrorTol, Ceres function_tolerance, scipy ftol; scipy also gets
    Ceres' default parameter and gradient tolerances as xtol and gtol). scipy past --scipy-cap seconds
    is stopped and reported as "> cap" with its best state;
(b) time to the first state whose cost is within 1 % of the best final cost of all solvers, from each
    solver's trace: ours, GTSAM's graph error after each iteration (bundle_adjust's on_iteration hook;
    the gauge priors add a negligible amount); Ceres, the cost an IterationCallback sees after each
    iteration; scipy, every residual evaluation that lowers the cost. Where the initial state is
    already within 1 % (Unity Hall: its global BA lowers the cost by 0.6 %), (b) is n/a.

Problems: Unity Hall as the pipeline has it just before its global BA; synthetic make_scene problems
(cameras on a ring around a cube of points, each point seen by ~8 random cameras, 1 px noise) started
from cameras moved by ~0.6 deg / 0.05 units and points by 0.03 units (the scene is ~2 units, cameras
~6 away). --repeat N keeps the fastest (CPU) of N runs of ours and of Ceres.

    python benchmarks/bench_bundle_adjustment.py                     # Unity Hall, 50x10000, 200x50000
    python benchmarks/bench_bundle_adjustment.py --quick             # Unity Hall and 20x2000 only
    python benchmarks/bench_bundle_adjustment.py --sizes 50x10000 --no-unity-hall --scipy-cap 120
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")  # one thread each, before numpy loads BLAS

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.sparse import lil_matrix  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimation.bundle_adjustment.factor_graph import bundle_adjust, huber_cost, reprojection_residuals, rms  # noqa: E402
from estimation.config import BundleAdjustmentConfig  # noqa: E402
from estimation.synthetic import make_scene  # noqa: E402
from estimation.types import CameraPose  # noqa: E402

SAME_COST_TOLERANCE = 0.01
"""The issue's criterion: ours and Ceres reach 'the same final cost' when they differ by at most 1 %."""
CERES_PARAMETER_TOLERANCE = 1e-8
CERES_GRADIENT_TOLERANCE = 1e-10
"""Ceres' default parameter and gradient tolerances, given to scipy's xtol and gtol (GTSAM has none)."""
TARGET_OURS_OVER_CERES_TIME = 1.5
TARGET_SCIPY_OVER_OURS_TIME = 5.0


@dataclass(frozen=True)
class Problem:
    """A bundle adjustment problem: initial cameras and points, and the observations."""

    name: str
    K: np.ndarray
    poses: list[CameraPose]
    points: np.ndarray
    camera_index: np.ndarray
    point_index: np.ndarray
    uv: np.ndarray
    scale_reference: int = 1


@dataclass(frozen=True)
class Run:
    """What one solver did with one problem."""

    solver: str
    poses: list[CameraPose] | None
    points: np.ndarray | None
    iterations: int
    wall_s: float
    cpu_s: float
    trace: tuple[tuple[float, float, float], ...]  # (cpu s, wall s, cost) after each iteration, from 0
    note: str = ""
    build_wall_s: float = 0.0  # problem construction, when not included in wall_s / cpu_s
    build_cpu_s: float = 0.0
    capped: bool = False


# ----------------------------------------------------------------------------------------------- problems


def synthetic_problem(
    num_cameras: int,
    num_points: int,
    track_length: float,
    noise_px: float,
    outlier_fraction: float,
    seed: int = 0,
) -> Problem:
    """make_scene with ~track_length observations per point, then every camera but 0 and every point moved."""
    scene = make_scene(
        num_cameras=num_cameras,
        num_points=num_points,
        noise_px=noise_px,
        outlier_fraction=outlier_fraction,
        seed=seed,
        visibility=min(1.0, track_length / num_cameras),
    )
    rng = np.random.default_rng(seed + 1)
    poses = [scene.poses[0]] + [
        CameraPose.from_center(
            Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ pose.R,
            pose.center + rng.normal(0, 0.05, 3),
        )
        for pose in scene.poses[1:]
    ]
    points = scene.points + rng.normal(0, 0.03, scene.points.shape)
    tracks = scene.tracks
    return Problem(
        f"synthetic {num_cameras}x{num_points}",
        scene.K,
        poses,
        points,
        tracks.image_index,
        tracks.track_index,
        tracks.uv,
    )


def unity_hall_problem(data_dir: Path) -> Problem:
    """The Unity Hall reconstruction just before its global BA (inputs of the pipeline's first global BA)."""
    import estimation.bundle_adjustment.factor_graph as bundle_adjustment_module
    from estimation.config import ReconstructionConfig
    from estimation.geometry.projection import as_camera, is_shared
    from estimation.io.images import find_calibration, list_images
    from estimation.mapper.incremental import run_incremental
    from estimation.pipeline import extract_tracks

    calls: list[dict] = []
    original = bundle_adjustment_module.bundle_adjust

    def recording(
        camera, poses, points, camera_index, point_index, uv, config, fixed_cameras=(0,), scale_reference=1,
        **options,
    ):
        calls.append(
            {
                "K": as_camera(camera if is_shared(camera) else camera[0]).K,
                "poses": list(poses),
                "points": np.array(points),
                "camera_index": camera_index,
                "point_index": point_index,
                "uv": uv,
                "fixed": list(fixed_cameras),
                "scale_reference": scale_reference,
            }
        )
        return original(
            camera, poses, points, camera_index, point_index, uv, config, fixed_cameras, scale_reference,
            **options,
        )

    config = ReconstructionConfig(write_figures=False)
    images = list_images(data_dir)
    K = find_calibration(data_dir, None)
    tracks = extract_tracks(images, config).tracks
    bundle_adjustment_module.bundle_adjust = recording
    try:
        model = run_incremental(tracks, K, config)
    finally:
        bundle_adjustment_module.bundle_adjust = original
    registered = len(model.poses)
    global_calls = [c for c in calls if len(c["poses"]) == registered and c["scale_reference"] is not None]
    if not global_calls:
        raise RuntimeError("the pipeline made no global bundle adjustment call to record")
    call = global_calls[0]
    return Problem(
        "Unity Hall (before global BA)",
        call["K"],
        call["poses"],
        call["points"],
        np.asarray(call["camera_index"]),
        np.asarray(call["point_index"]),
        np.asarray(call["uv"]),
        scale_reference=call["scale_reference"],
    )


def problem_cost(
    problem: Problem, poses: list[CameraPose], points: np.ndarray, config: BundleAdjustmentConfig
) -> tuple[float, float]:
    """(Huber cost, RMS px) of poses/points on the problem's observations, the same function for all."""
    residuals = reprojection_residuals(
        problem.K, poses, points, problem.camera_index, problem.point_index, problem.uv
    )
    return huber_cost(residuals, config.huber_threshold_px, config.measurement_sigma_px), rms(residuals)


def scale_coordinate(problem: Problem) -> int:
    """The translation coordinate of the scale-reference camera that moves most when the scene scales
    about camera 0: d t_ref / d s = -R_ref (C_ref - C_0)."""
    reference = problem.poses[problem.scale_reference]
    return int(np.argmax(np.abs(reference.R @ (reference.center - problem.poses[0].center))))


# ------------------------------------------------------------------------------------------------ solvers


class Clock:
    """CPU and wall seconds since construction; `record(cost)` appends (cpu s, wall s, cost) to `trace`."""

    def __init__(self) -> None:
        self.cpu0, self.wall0 = time.process_time(), time.perf_counter()
        self.trace: list[tuple[float, float, float]] = []

    def elapsed(self) -> tuple[float, float]:
        return time.process_time() - self.cpu0, time.perf_counter() - self.wall0

    def record(self, cost: float) -> None:
        self.trace.append((*self.elapsed(), cost))


def solve_ours(problem: Problem, config: BundleAdjustmentConfig) -> Run:
    """bundle_adjust from the arrays (graph construction and result extraction included in its times)."""
    initial_cost = problem_cost(problem, problem.poses, problem.points, config)[0]
    clock = Clock()
    clock.trace.append((0.0, 0.0, initial_cost))
    result = bundle_adjust(
        problem.K,
        problem.poses,
        problem.points,
        problem.camera_index,
        problem.point_index,
        problem.uv,
        config,
        fixed_cameras=(0,),
        scale_reference=problem.scale_reference,
        on_iteration=lambda _iteration, error: clock.record(error),
    )
    cpu, wall = clock.elapsed()
    return Run(
        f"ours GTSAM {config.linear_solver}",
        result.poses,
        result.points,
        result.iterations,
        wall,
        cpu,
        tuple(clock.trace),
        note=f"{config.ordering}, {config.linear_solver}",
    )


def solve_ceres(problem: Problem, config: BundleAdjustmentConfig, linear_solver: str) -> Run:
    import pyceres
    import pycolmap
    from pycolmap.cost_functions import ReprojErrorCost

    start, start_cpu = time.perf_counter(), time.process_time()
    K = problem.K
    rotations = [Rotation.from_matrix(pose.R).as_quat() for pose in problem.poses]  # (x, y, z, w), Eigen's
    translations = [pose.t.copy() for pose in problem.poses]
    points = [point.copy() for point in problem.points]
    intrinsics = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    ceres_problem = pyceres.Problem()
    loss = pyceres.HuberLoss(config.huber_threshold_px)
    pinhole = pycolmap.CameraModelId.PINHOLE
    for camera, point, uv in zip(
        problem.camera_index.tolist(), problem.point_index.tolist(), problem.uv, strict=True
    ):
        ceres_problem.add_residual_block(
            ReprojErrorCost(pinhole, uv),
            loss,
            [rotations[camera], translations[camera], points[point], intrinsics],
        )
    ceres_problem.set_parameter_block_constant(intrinsics)
    for camera in sorted(set(problem.camera_index.tolist())):
        ceres_problem.set_manifold(rotations[camera], pyceres.EigenQuaternionManifold())
    ceres_problem.set_parameter_block_constant(rotations[0])
    ceres_problem.set_parameter_block_constant(translations[0])
    ceres_problem.set_manifold(
        translations[problem.scale_reference], pyceres.SubsetManifold(3, [scale_coordinate(problem)])
    )
    build_wall, build_cpu = time.perf_counter() - start, time.process_time() - start_cpu

    class Recorder(pyceres.IterationCallback):
        """Ceres calls this after iteration 0 (the initial evaluation) and after every later one."""

        def __call__(self, summary: pyceres.IterationSummary) -> pyceres.CallbackReturnType:
            clock.record(summary.cost)
            return pyceres.CallbackReturnType.SOLVER_CONTINUE

    recorder = Recorder()
    options = pyceres.SolverOptions()
    options.linear_solver_type = getattr(pyceres.LinearSolverType, linear_solver)
    options.num_threads = 1
    options.max_num_iterations = config.max_iterations
    options.function_tolerance = config.relative_error_tol  # gradient / parameter tolerances: defaults
    options.callbacks = [recorder]
    summary = pyceres.SolverSummary()
    clock = Clock()
    pyceres.solve(options, ceres_problem, summary)
    cpu, wall = clock.elapsed()
    poses = [
        CameraPose(Rotation.from_quat(q).as_matrix(), t) for q, t in zip(rotations, translations, strict=True)
    ]
    return Run(
        f"ceres {linear_solver}",
        poses,
        np.array(points),
        summary.num_successful_steps + summary.num_unsuccessful_steps,
        wall,
        cpu,
        tuple(clock.trace),
        note=summary.termination_type.name,
        build_wall_s=build_wall,
        build_cpu_s=build_cpu,
    )


class _CapReached(Exception):
    pass


def solve_scipy(problem: Problem, config: BundleAdjustmentConfig, cap_s: float) -> Run:
    """least_squares (trf, sparse finite-difference Jacobian) to its own convergence or the cap; every
    residual evaluation that lowers the cost is traced."""
    num_cameras, num_points = len(problem.poses), len(problem.points)
    held = scale_coordinate(problem)
    # Camera parameters: rotation vector (3) and translation (3) of every camera but 0; one translation
    # coordinate of the scale-reference camera is held. Then the points (3 each).
    camera_mask = np.ones((num_cameras, 6), bool)
    camera_mask[0] = False
    camera_mask[problem.scale_reference, 3 + held] = False
    camera_columns = -np.ones((num_cameras, 6), int)
    camera_columns[camera_mask] = np.arange(camera_mask.sum())
    num_camera_params = int(camera_mask.sum())
    camera_params0 = np.stack(
        [np.concatenate([Rotation.from_matrix(p.R).as_rotvec(), p.t]) for p in problem.poses]
    )
    x0 = np.concatenate([camera_params0[camera_mask], problem.points.ravel()])
    k = config.huber_threshold_px

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cameras = camera_params0.copy()
        cameras[camera_mask] = x[:num_camera_params]
        return cameras, x[num_camera_params:].reshape(num_points, 3)

    def rotate(points: np.ndarray, rotvecs: np.ndarray) -> np.ndarray:
        """Rodrigues' formula on each row: R(w) X."""
        theta = np.linalg.norm(rotvecs, axis=1)[:, None]
        with np.errstate(invalid="ignore", divide="ignore"):
            axis = np.nan_to_num(rotvecs / theta)
        dot = np.sum(points * axis, axis=1)[:, None]
        return (
            np.cos(theta) * points + np.sin(theta) * np.cross(axis, points) + dot * (1 - np.cos(theta)) * axis
        )

    best = {"cost": np.inf, "x": x0}

    def residuals(x: np.ndarray) -> np.ndarray:
        cameras, points = unpack(x)
        cam = cameras[problem.camera_index]
        x_cam = rotate(points[problem.point_index], cam[:, :3]) + cam[:, 3:]
        x_img = x_cam @ problem.K.T
        r = x_img[:, :2] / x_img[:, 2:3] - problem.uv
        norm = np.linalg.norm(r, axis=1)
        # sqrt(2 huber_k(|r|)) / |r| scales r so that 0.5 |r'|^2 = huber_k(|r|) (the 2-vector Huber loss).
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(norm <= k, 1.0, np.sqrt(np.maximum(2 * k * norm - k * k, 0.0)) / norm)
        robust = (r * scale[:, None]).ravel()
        cost = 0.5 * float(robust @ robust)
        if cost < best["cost"]:
            best.update(cost=cost, x=x.copy())
            clock.record(cost)
        if clock.elapsed()[1] > cap_s:
            raise _CapReached
        return robust

    sparsity = lil_matrix((2 * len(problem.uv), len(x0)), dtype=int)
    rows = np.arange(len(problem.uv))
    for column in range(6):
        columns = camera_columns[problem.camera_index, column]
        ok = columns >= 0
        for row_offset in (0, 1):
            sparsity[2 * rows[ok] + row_offset, columns[ok]] = 1
    for column in range(3):
        for row_offset in (0, 1):
            sparsity[2 * rows + row_offset, num_camera_params + 3 * problem.point_index + column] = 1

    clock = Clock()
    capped, iterations = False, 0
    try:
        result = least_squares(
            residuals,
            x0,
            jac_sparsity=sparsity,
            method="trf",
            x_scale="jac",
            loss="linear",
            ftol=config.relative_error_tol,  # the same relative cost decrease as GTSAM's and Ceres' stop
            xtol=CERES_PARAMETER_TOLERANCE,
            gtol=CERES_GRADIENT_TOLERANCE,
            max_nfev=100_000,
        )
        iterations = int(result.njev)
    except _CapReached:
        capped = True
    cpu, wall = clock.elapsed()
    cameras, points = unpack(best["x"])
    poses = [CameraPose(Rotation.from_rotvec(c[:3]).as_matrix(), c[3:]) for c in cameras]
    return Run(
        "scipy least_squares",
        poses,
        points,
        iterations,
        wall,
        cpu,
        tuple(clock.trace),
        note=f"stopped at the {cap_s:g} s cap, best state so far" if capped else "",
        capped=capped,
    )


# ------------------------------------------------------------------------------------------------ report


def first_reach(run: Run, threshold: float) -> tuple[float, float] | None:
    """(cpu s, wall s) of the first traced state whose cost is <= threshold; None if never."""
    return next(((cpu, wall) for cpu, wall, cost in run.trace if cost <= threshold), None)


def reach_cpu(reached: tuple[float, float] | None) -> float | None:
    return None if reached is None else reached[0]


def quotient(numerator: float | None, denominator: float | None) -> float | None:
    """numerator / denominator; None when either is unknown or the denominator is 0 (reached at start)."""
    if numerator is None or denominator is None or denominator <= 0:
        return None
    return numerator / denominator


def ratio_text(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}x"


def verdict(value: float | None, target: float, at_most: bool) -> str:
    if value is None:
        return "n/a"
    return "met" if (value <= target if at_most else value >= target) else "NOT met"


def print_verdicts(
    ours: Run,
    ceres_runs: list[Run],
    scipy_run: Run | None,
    costs: dict[str, tuple[float, float]],
    reach: dict[str, tuple[float, float] | None],
    reach_applicable: bool,
) -> None:
    """The issue's two targets for one of our runs, by (a) time to convergence and (b) time to 1 %.
    (b) never reached by ours: NOT met; never reached by scipy: its whole time is a lower bound."""
    ours_cost = costs[ours.solver][0]
    ceres_full = min(ceres_runs, key=lambda run: run.cpu_s)  # each column against Ceres' fastest for it
    ceres_cost = costs[ceres_full.solver][0]
    same_cost = abs(ours_cost - ceres_cost) <= SAME_COST_TOLERANCE * ceres_cost
    full_ratio = ours.cpu_s / ceres_full.cpu_s
    ours_reach = reach_cpu(reach[ours.solver])
    ceres_reach_times = [t for t in (reach_cpu(reach[run.solver]) for run in ceres_runs) if t is not None]
    ceres_reach = min(ceres_reach_times, default=None)
    reach_ratio = quotient(ours_reach, ceres_reach)
    if reach_applicable and ours_reach is None:
        reach_verdict = "NOT met: ours never got there"
    else:
        reach_verdict = verdict(reach_ratio, TARGET_OURS_OVER_CERES_TIME, at_most=True)
    print(
        f"{ours.solver} vs Ceres: final cost ours/{ceres_full.solver} {ours_cost / ceres_cost:.6f} "
        f"(same within 1 %: {'yes' if same_cost else 'NO'}); target ours <= "
        f"{TARGET_OURS_OVER_CERES_TIME}x Ceres: (a) cpu {full_ratio:.2f}x {ceres_full.solver} "
        f"[{verdict(full_ratio if same_cost else None, TARGET_OURS_OVER_CERES_TIME, at_most=True)}], "
        f"(b) cpu {ratio_text(reach_ratio)} Ceres' fastest "
        f"[{reach_verdict}]; "
        f"(a) wall {ours.wall_s / ceres_full.wall_s:.2f}x; (a) cpu with Ceres' problem building added "
        f"{ours.cpu_s / (ceres_full.cpu_s + ceres_full.build_cpu_s):.2f}x"
    )
    if scipy_run is not None:
        full_speedup = scipy_run.cpu_s / ours.cpu_s
        scipy_reach = reach_cpu(reach[scipy_run.solver])
        reach_speedup = quotient(scipy_run.cpu_s if scipy_reach is None else scipy_reach, ours_reach)
        lower_bound = scipy_run.capped or (reach_applicable and scipy_reach is None)
        print(
            f"scipy vs {ours.solver}: final cost scipy/ours {costs[scipy_run.solver][0] / ours_cost:.6f}; "
            f"target scipy >= {TARGET_SCIPY_OVER_OURS_TIME}x ours: (a) cpu {'> ' if scipy_run.capped else ''}"
            f"{full_speedup:.2f}x [{verdict(full_speedup, TARGET_SCIPY_OVER_OURS_TIME, at_most=False)}], "
            f"(b) cpu {'> ' if lower_bound else ''}{ratio_text(reach_speedup)} "
            f"[{verdict(reach_speedup, TARGET_SCIPY_OVER_OURS_TIME, at_most=False)}]"
            + ("; scipy never reached the (b) threshold" if reach_applicable and scipy_reach is None else ""),
            flush=True,
        )


def benchmark(
    problem: Problem,
    ours_configs: list[BundleAdjustmentConfig],
    ceres_solvers: list[str],
    scipy_cap_s: float,
    with_scipy: bool,
    repeat: int = 1,
) -> None:
    print(
        f"\n## {problem.name}: {len(problem.poses)} cameras, {len(problem.points)} points, "
        f"{len(problem.uv)} observations; load average {os.getloadavg()[0]:.2f} (1 min) before",
        flush=True,
    )
    config = ours_configs[0]  # the cost and stopping settings are the same in every ours config
    initial_cost, initial_rms = problem_cost(problem, problem.poses, problem.points, config)
    print(f"initial cost {initial_cost:.6g}, RMS {initial_rms:.3f} px", flush=True)

    def fastest(solve: Callable[[], Run]) -> Run:
        """The least CPU time of `repeat` runs (on a shared machine the minimum is the cleanest figure)."""
        return min((solve() for _ in range(repeat)), key=lambda run: run.cpu_s)

    ours_runs = [fastest(lambda ours=ours: solve_ours(problem, ours)) for ours in ours_configs]
    ceres_runs = [
        fastest(lambda solver=solver: solve_ceres(problem, config, solver)) for solver in ceres_solvers
    ]
    runs = [*ours_runs, *ceres_runs]
    if with_scipy:
        runs.append(solve_scipy(problem, config, scipy_cap_s))
    costs = {run.solver: problem_cost(problem, run.poses, run.points, config) for run in runs}
    best_cost = min(cost for cost, _ in costs.values())
    threshold = best_cost * (1 + SAME_COST_TOLERANCE)
    # Where the initial state is already within 1 % (Unity Hall: its global BA lowers the cost < 1 %),
    # every solver "reaches" it at once and (b) says nothing: it is then reported as n/a.
    reach = {
        run.solver: None if initial_cost <= threshold else first_reach(run, threshold) for run in runs
    }
    if initial_cost <= threshold:
        print(f"(b) n/a: the initial cost {initial_cost:.6g} is already within 1 % of the best final cost")

    print(
        f"(a) = to the solver's own convergence (relative cost decrease < {config.relative_error_tol:g}); "
        f"(b) = to the first state with cost <= 1.01 x the best final cost of all solvers "
        f"({threshold:.6g}). CPU seconds = process time of the solve (ours: from the arrays, graph "
        f"construction included; Ceres: pyceres.solve only, building the problem is in notes)."
    )
    header = (
        f"{'solver':<34}{'iters':>6}{'(a) cpu s':>11}{'(a) wall s':>11}{'final cost':>13}{'cost/best':>11}"
        f"{'RMS px':>8}{'(b) cpu s':>11}{'(b) wall s':>11}  notes"
    )
    print(header)
    print("-" * len(header))
    for run in runs:
        cost, run_rms = costs[run.solver]
        reached = reach[run.solver]
        if initial_cost <= threshold:
            reached_cpu, reached_wall = "n/a", "n/a"
        else:
            reached_cpu, reached_wall = ("never",) * 2 if reached is None else (f"{t:.2f}" for t in reached)
        bound = "> " if run.capped else ""
        built = run.build_wall_s > 0
        extra = f"; build {run.build_cpu_s:.2f} s cpu {run.build_wall_s:.2f} s wall" if built else ""
        print(
            f"{run.solver:<34}{run.iterations:>6}{bound + f'{run.cpu_s:.2f}':>11}"
            f"{bound + f'{run.wall_s:.2f}':>11}{cost:>13.7g}{cost / best_cost:>11.6f}{run_rms:>8.3f}"
            f"{reached_cpu:>11}{reached_wall:>11}  {run.note}{extra}"
        )

    for ours in ours_runs:
        print_verdicts(
            ours, ceres_runs, runs[-1] if with_scipy else None, costs, reach, initial_cost > threshold
        )
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) after this problem", flush=True)


def parse_size(text: str) -> tuple[int, int]:
    cameras, points = text.lower().split("x")
    return int(cameras), int(points)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes",
        default="50x10000,200x50000",
        help="synthetic problems CAMERASxPOINTS, comma separated (empty: none)",
    )
    parser.add_argument("--quick", action="store_true", help="Unity Hall and a 20x2000 problem only")
    parser.add_argument("--no-unity-hall", action="store_true", help="skip the Unity Hall problem")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "unity_hall")
    parser.add_argument("--track-length", type=float, default=8.0, help="observations per synthetic point")
    parser.add_argument("--noise-px", type=float, default=1.0)
    parser.add_argument("--outliers", type=float, default=0.0, help="fraction of random-pixel observations")
    parser.add_argument("--scipy-cap", type=float, default=600.0, help="seconds before scipy is stopped")
    parser.add_argument("--no-scipy", action="store_true")
    parser.add_argument("--repeat", type=int, default=1, help="runs of ours and Ceres; the fastest is kept")
    parser.add_argument(
        "--ceres-solvers",
        default="DENSE_SCHUR,SPARSE_SCHUR,ITERATIVE_SCHUR",
        help="Ceres linear solvers to run, comma separated; the fastest is the reference",
    )
    parser.add_argument("--ordering", default=None, help="override BundleAdjustmentConfig.ordering")
    parser.add_argument(
        "--linear-solvers",
        default=None,
        help="BundleAdjustmentConfig.linear_solver of each 'ours' run, comma separated (default: the "
        "config's default, then pcg_block_jacobi)",
    )
    args = parser.parse_args()

    config = BundleAdjustmentConfig(**({} if args.ordering is None else {"ordering": args.ordering}))
    linear_solvers = (
        [config.linear_solver, "pcg_block_jacobi"]
        if args.linear_solvers is None
        else [name.strip() for name in args.linear_solvers.split(",") if name.strip()]
    )
    ours_configs = [
        BundleAdjustmentConfig(**{**config.model_dump(), "linear_solver": name})
        for name in dict.fromkeys(linear_solvers)
    ]
    sizes = ["20x2000"] if args.quick else [s for s in args.sizes.split(",") if s.strip()]
    print(f"bundle adjustment benchmark; config {config.model_dump()}")
    print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} (1 min) at start")

    problems = [] if args.no_unity_hall else [lambda: unity_hall_problem(args.data)]
    problems += [
        (
            lambda size=size: synthetic_problem(
                *parse_size(size), args.track_length, args.noise_px, args.outliers
            )
        )
        for size in sizes
    ]
    ceres_solvers = [name.strip() for name in args.ceres_solvers.split(",") if name.strip()]
    try:
        import pyceres  # noqa: F401
        import pycolmap.cost_functions  # noqa: F401
    except ImportError as error:
        raise SystemExit(
            f"Ceres needs pyceres and pycolmap 3.13 (pip install pyceres 'pycolmap==3.13.0'): {error}"
        ) from error
    for make_problem in problems:
        try:
            problem = make_problem()
        except Exception as error:  # noqa: BLE001 - e.g. the pipeline fails on the data: say so, go on
            print(f"\nproblem unavailable: {type(error).__name__}: {error}")
            continue
        benchmark(problem, ours_configs, ceres_solvers, args.scipy_cap, not args.no_scipy, args.repeat)
    print(f"\nload average {os.getloadavg()[0]:.2f} (1 min) at the end")


if __name__ == "__main__":
    main()
