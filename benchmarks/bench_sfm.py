"""Structure from Motion end to end, ours (`estimation.reconstruct`) beside pycolmap on the same images.

For each set, both run from the image files with the same fixed intrinsics (with --uncalibrated, from
the same focal length prior instead, each refining it with a radial distortion): ours with SIFT (or the
course's match files for Unity Hall), pycolmap with its own pipeline (SIFT extraction, exhaustive matching,
incremental mapping, intrinsics held fixed). The table gives registered images, the mean and max rotation
error and camera-centre error against the ground truth after a similarity alignment of the registered
centres (estimation.geometry.alignment.aligned_pose_errors), the mean rotation error of every pair's
relative rotation (no alignment: on a few nearly collinear centres the similarity's own rotation error can
be most of the aligned figure; `relative_rotation_errors_deg`), points, mean track length, seconds and the
ratio ours / pycolmap. "Ceres left" starts pycolmap's bundle adjuster (Ceres, Huber loss at our
huber_threshold_px, intrinsics fixed) from our exported model and prints the share of the cost it still
removes: below 1 % means our final bundle adjustment converged.

Sets (../shared/data):
- lego: lego_200 train + val (90 views, 200x200 RGBA composited on white), K from camera_angle_x; the
  ground-truth camera-to-world matrices (OpenGL axes) are converted once to world-to-camera OpenCV poses.
  Pixel conventions: our keypoints put the top-left pixel's centre at (0, 0), so the principal point of
  the image centre is ((W - 1) / 2, (H - 1) / 2) for us and (W / 2, H / 2) for COLMAP (centre at 0.5).
- fountain, herzjesu: strecha/fountain-P11 and Herz-Jesus-P8 at full size with their calibration.txt
  (COLMAP's pixel convention: - 0.5 for ours, `STRECHA_PIXEL_OFFSET`) and ground_truth.json.
- ring: lego_ring_400 (50 views of lego's validation ring at 400 px, about 7 deg apart) with its
  calibration.txt and ground_truth.json: a sparse ring around a symmetric object, where a flipped camera
  (registered on the far side of the ring) is the failure to watch for (rot max).
- ring16, darkring: 16 of lego_ring_400's views, every 50/16-th in the order of their azimuth (a sparse
  capture all around the object, at 8-79 deg elevation), as they are (ring16) and made dark and flat
  (darkring): the object at a quarter of its brightness on a near-black background (the white background
  blended to grey level 8), with sensor noise (sigma 1 grey level): a dark, low-texture object, where few
  features pass SIFT's contrast threshold and the background must produce no matches.
- ringN, darkringN (N < 50): the same with N views, every 50/N-th from the --ring-offset-th on: sparse
  rings of other spacings and starts (ring25 --ring-offset 1: the 25 views that ring25 leaves out), where
  a camera more than WRONG_DEG off (flipped, or placed by a wrong pose) is the failure to watch for.
- box, boxN, boxN_seedS: a rendered box whose opposite sides look alike
  (`estimation.synthetic.render_box_ring`: one texture per pair of opposite sides but for 8 marks of each, a
  ground of tiled random marks) seen from 36 (N) cameras on a ring at 400 px, rendered with seed 0 (S):
  views half a turn apart look alike, so every camera has a look-alike twin across the ring. Ours prints
  report.json's warning when it finds the model folded onto itself, and what it did where its look-alike
  check's strongest pairs conflicted.
- unity: Unity Hall with the course's match files (ours only; no ground truth: RMS and Ceres left).

Ours also prints the three registrations whose inliers pinned the rotation least (report.json's
`registration_rotation_std_deg`, the figure `MapperConfig.verify_max_rotation_std_deg` limits).

    python benchmarks/bench_sfm.py                 # every set
    python benchmarks/bench_sfm.py --sets lego --no-pycolmap
    python benchmarks/bench_sfm.py --sets fountain --max-reprojection-sigmas 0
    python benchmarks/bench_sfm.py --sets lego --no-pycolmap --seeds 0,1,2,3,4,5,6,7,8,9   # RANSAC seeds
    python benchmarks/bench_sfm.py --sets lego --no-pycolmap --mapper '{"relaxed_registration_factor": 0.9}'
    python benchmarks/bench_sfm.py --sets lego --repeats 5   # median seconds
    python benchmarks/bench_sfm.py --sets lego --uncalibrated  # from the prior
    python benchmarks/bench_sfm.py --sets ring20,ring25,ring33 --ring-offset 1 --seeds 0,1   # sparse rings
    python benchmarks/bench_sfm.py --sets box,box24    # look-alike sides, rendered

One run's seconds move by ~10 % from run to run on a 2-core machine (pycolmap's too); with --repeats N,
ours and pycolmap run N times each, one after the other, and the first seed's row gives the median seconds
of each and the median of the N paired ratios.
"""

from __future__ import annotations

import os

os.environ.setdefault("GLOG_minloglevel", "2")  # pycolmap: warnings and errors only, before it loads

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import re  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from estimation import ReconstructionConfig, reconstruct  # noqa: E402
from estimation.config import BundleAdjustmentConfig  # noqa: E402
from estimation.geometry.alignment import aligned_pose_errors, relative_rotation_errors_deg  # noqa: E402
from estimation.io.export import opengl_c2w_to_opencv_pose  # noqa: E402
from estimation.mapper.verification import FOLDED  # noqa: E402
from estimation.synthetic import render_box_ring  # noqa: E402
from estimation.types import CameraPose  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}
COLMAP_PIXEL_OFFSET = 0.5
"""COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we put it at (0, 0)."""


@dataclass(frozen=True)
class BenchSet:
    """Images, their fixed intrinsics in our pixel convention, and the true poses by file name."""

    name: str
    images: Path
    K: np.ndarray
    truth: dict[str, CameraPose] | None
    features: str = "sift"
    calibrated: bool = True      # False: `images` has no calibration.txt; both methods refine a prior


@dataclass(frozen=True)
class Outcome:
    """What one method reconstructed, and how long it took."""

    poses: dict[str, CameraPose]
    points: int
    mean_track_length: float
    seconds: float
    rms_px: float = float("nan")
    ceres_left: float = float("nan")
    stage_seconds: dict[str, float] | None = None
    cpu_seconds: tuple[float, float] | None = None     # this process's, its worker processes'
    focal_px: float = float("nan")                      # the refined focal length (uncalibrated runs)
    # the largest rotation std-devs (deg at 1 px) the registrations' inliers allowed, by image (ours)
    loosest_registrations: dict[str, float] | None = None
    fold_warnings: list[str] | None = None               # report.json's "possibly folded" warnings
    look_alike_check: str = ""                           # report.json's features.look_alike_check
    conflicts_outcome: str = ""                          # its look_alike_conflicts_outcome, if any


def lego_set(work: Path) -> BenchSet:
    """lego_200 train + val composited on white into `work`, K from camera_angle_x, true poses."""
    source = DATA / "lego_200"
    folder = work / "lego"
    folder.mkdir(parents=True, exist_ok=True)
    truth, K = {}, None
    for split in ("train", "val"):
        meta = json.loads((source / f"transforms_{split}.json").read_text())
        for frame in meta["frames"]:
            name = Path(frame["file_path"]).name + ".png"
            rgba = np.asarray(Image.open(source / split / name).convert("RGBA"), float) / 255.0
            rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
            Image.fromarray(np.rint(rgb * 255).astype(np.uint8)).save(folder / name)
            truth[name] = opengl_c2w_to_opencv_pose(np.array(frame["transform_matrix"]))
            height, width = rgba.shape[:2]
            focal = 0.5 * width / np.tan(0.5 * meta["camera_angle_x"])
            K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    np.savetxt(folder / "calibration.txt", K)
    return BenchSet("lego_200 (90)", folder, K, truth)


def linked_images(source: Path, folder: Path) -> Path:
    """`folder` holding a link to each image of `source` (nothing else of it)."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in source.iterdir():
        if path.suffix.lower() in IMAGE_SUFFIXES and not (folder / path.name).exists():
            (folder / path.name).symlink_to(path.resolve())
    return folder


def uncalibrated_copy(bench: BenchSet, work: Path) -> BenchSet:
    """The set's images linked into `work` without calibration.txt (no EXIF either): focal length from
    the 1.2 max(w, h) prior, refined with a radial distortion by both methods; K stays the truth."""
    folder = linked_images(bench.images, work / f"{bench.images.name}_uncalibrated")
    return replace(bench, name=f"{bench.name} uncalibrated", images=folder, calibrated=False)


def ground_truth_set(folder: Path, name: str) -> BenchSet:
    """A folder with calibration.txt and ground_truth.json (world-to-camera R, t per image)."""
    cameras = json.loads((folder / "ground_truth.json").read_text())["cameras"]
    truth = {image: CameraPose(R=np.array(c["R"], float), t=np.array(c["t"], float))
             for image, c in cameras.items()}
    return BenchSet(name, folder, np.loadtxt(folder / "calibration.txt"), truth)


SPARSE_RING_VIEWS = 16
SPARSE_RING = re.compile(r"(dark)?ring(\d+)?")
"""ring16, darkring, ringN, darkringN: a sparse ring of lego_ring_400 (`sparse_ring_set`)."""
WRONG_DEG = 5.0
"""A registered camera more rotation error than this is placed wrongly (the issue's target: none)."""
DARK_RING_GAIN = 0.25
DARK_RING_BACKGROUND = 8.0
DARK_RING_NOISE_SIGMA = 1.0


def sparse_ring_set(work: Path, dark: bool, views: int = SPARSE_RING_VIEWS, offset: int = 0) -> BenchSet:
    """`views` lego_ring_400 views spread in azimuth, every len/views-th from the offset-th on, copied (or
    darkened) into `work` (see the module docstring)."""
    ring = ground_truth_set(DATA / "lego_ring_400", "lego_ring_400")
    centres = {name: -pose.R.T @ pose.t for name, pose in ring.truth.items()}
    by_azimuth = sorted(centres, key=lambda name: np.arctan2(centres[name][1], centres[name][0]))
    if not 3 <= views < len(by_azimuth):
        raise SystemExit(f"a sparse ring takes 3 to {len(by_azimuth) - 1} views, not {views}")
    chosen = [by_azimuth[(round(k * len(by_azimuth) / views) + offset) % len(by_azimuth)]
              for k in range(views)]
    folder = work / f"{'dark_' if dark else ''}ring_{views}_{offset}"
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for name in chosen:
        rgb = np.asarray(Image.open(ring.images / name).convert("RGB"), float)
        if dark:
            white = np.clip((rgb.min(axis=2, keepdims=True) - 235.0) / 20.0, 0.0, 1.0)  # background and edges
            rgb = DARK_RING_GAIN * rgb * (1.0 - white) + DARK_RING_BACKGROUND * white
            rgb += rng.normal(0.0, DARK_RING_NOISE_SIGMA, rgb.shape)
        Image.fromarray(np.clip(np.rint(rgb), 0, 255).astype(np.uint8)).save(folder / name)
    np.savetxt(folder / "calibration.txt", ring.K)
    truth = {name: ring.truth[name] for name in chosen}
    start = f", from {offset}" if offset else ""
    return BenchSet(f"lego_ring_400 {'dark ' if dark else ''}({views}{start})", folder, ring.K, truth)


BOX = re.compile(r"box(\d+)?(?:_seed(\d+))?")
"""box, boxN, boxN_seedS: the rendered box with look-alike sides (`box_ring_set`)."""
BOX_VIEWS = 36


def box_ring_set(work: Path, views: int, seed: int = 0) -> BenchSet:
    """`render_box_ring`'s views (rendered with `seed`) written into `work` with calibration.txt and their
    true poses."""
    ring = render_box_ring(num_views=views, seed=seed)
    folder = work / f"box_{views}_seed{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    truth = {}
    for k, (rgb, pose) in enumerate(zip(ring.images, ring.poses, strict=True)):
        name = f"view_{k:03d}.png"
        Image.fromarray(rgb).save(folder / name)
        truth[name] = pose
    np.savetxt(folder / "calibration.txt", ring.K)
    rendered = f", seed {seed}" if seed else ""
    return BenchSet(f"box with look-alike sides ({views}{rendered})", folder, ring.K, truth)


STRECHA_PIXEL_OFFSET = 0.5
"""Strecha's calibration.txt gives the principal point with the top-left pixel's centre at (0.5, 0.5), as
COLMAP does: both methods are more accurate with it read so than read in our convention (RESULTS)."""


def strecha_set(name: str, work: Path) -> BenchSet:
    """strecha/<name>'s photos linked into `work` with calibration.txt in our pixel convention (the data's K
    less STRECHA_PIXEL_OFFSET; pycolmap gets the data's K back), and its ground truth."""
    source = DATA / "strecha" / name
    bench = ground_truth_set(source, name)
    folder = linked_images(source, work / name)
    K = bench.K.copy()
    K[:2, 2] -= STRECHA_PIXEL_OFFSET
    np.savetxt(folder / "calibration.txt", K)
    return replace(bench, images=folder, K=K)


def run_ours(bench: BenchSet, out: Path, max_reprojection_sigmas: float | None = None, workers: int = 0,
             estimator: str | None = None, seed: int = 0, mapper: dict | None = None,
             sift: dict | None = None) -> Outcome:
    limit = {} if max_reprojection_sigmas is None else {"max_reprojection_sigmas": max_reprojection_sigmas}
    config = ReconstructionConfig(features=bench.features, write_figures=False, filter=limit,
                                  ransac={"seed": seed}, mapper=mapper or {},
                                  sift={"workers": workers, **(sift or {})},
                                  two_view={} if estimator is None else {"estimator": estimator})
    start, cpu, children = time.perf_counter(), time.process_time(), child_cpu_seconds()
    result = reconstruct(bench.images, out, config)
    seconds = time.perf_counter() - start
    # The worker process may still be exiting (reconstruct does not wait for it): its CPU counts once reaped.
    for child in multiprocessing.active_children():
        child.join()
    cpu_seconds = (time.process_time() - cpu, child_cpu_seconds() - children)
    names = result.model.image_names
    return Outcome(poses={names[m]: pose for m, pose in result.model.poses.items()},
                   points=result.report["points"], mean_track_length=result.report["mean_track_length"],
                   seconds=seconds, cpu_seconds=cpu_seconds,
                   rms_px=result.report["reprojection_error_px"]["after_ba"]["rms"],
                   ceres_left=ceres_cost_left(out / "sparse"),
                   stage_seconds={**result.report["seconds_per_stage"],
                                  **result.report["features"].get("seconds_per_stage", {})},
                   focal_px=float(result.K[0, 0]),
                   loosest_registrations=loosest_registrations(result.report),
                   fold_warnings=[warning for warning in result.report["warnings"]
                                  if warning.startswith(FOLDED)],
                   look_alike_check=result.report["features"].get("look_alike_check", ""),
                   conflicts_outcome=result.report["features"].get("look_alike_conflicts_outcome", ""))


LOOSEST_SHOWN = 3
"""Registrations listed by `loosest_registrations`."""


def loosest_registrations(report: dict) -> dict[str, float]:
    """The LOOSEST_SHOWN registrations of every model whose inliers pinned the rotation least (report.json's
    `registration_rotation_std_deg`), largest first."""
    stds = {name: std for model in report["models"]
            for name, std in model["registration_rotation_std_deg"].items()}
    return dict(sorted(stds.items(), key=lambda item: -item[1])[:LOOSEST_SHOWN])


def child_cpu_seconds() -> float:
    """User + system CPU seconds of this process's finished children (the worker processes)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def ceres_cost_left(sparse: Path) -> float:
    """(initial - final) / initial of Ceres' Huber cost, started from the exported model (poses and
    points free, intrinsics and the gauge of two cameras fixed)."""
    import pycolmap

    reconstruction = pycolmap.Reconstruction(str(sparse))
    options = pycolmap.BundleAdjustmentOptions(refine_focal_length=False, refine_principal_point=False,
                                               refine_extra_params=False, print_summary=False)
    options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
    options.ceres.loss_function_scale = BundleAdjustmentConfig().huber_threshold_px
    options.ceres.solver_options.function_tolerance = 1e-10
    options.ceres.solver_options.max_num_iterations = 200
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    summary = pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    ceres = getattr(summary, "ceres_summary", summary)
    return float((ceres.initial_cost - ceres.final_cost) / ceres.initial_cost)


def run_pycolmap(bench: BenchSet, work: Path) -> Outcome:
    """pycolmap's extraction, exhaustive matching and incremental mapping with K fixed; uncalibrated, with
    COLMAP's defaults (SIMPLE_RADIAL from its 1.2 max(w, h) prior, focal length and k refined, principal
    point held at the centre)."""
    import pycolmap

    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    K = bench.K
    params = [K[0, 0], K[1, 1], K[0, 2] + COLMAP_PIXEL_OFFSET, K[1, 2] + COLMAP_PIXEL_OFFSET]
    image_names = sorted(p.name for p in bench.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    database = work / "database.db"
    options = pycolmap.IncrementalPipelineOptions()
    if bench.calibrated:
        reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE",
                                             camera_params=",".join(map(str, params)))
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
    else:
        reader = pycolmap.ImageReaderOptions(camera_model="SIMPLE_RADIAL")
    start = time.perf_counter()
    pycolmap.extract_features(database, bench.images, image_names=image_names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    extracted = time.perf_counter()
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    matched = time.perf_counter()
    models = pycolmap.incremental_mapping(database, bench.images, work / "sparse", options=options)
    seconds = time.perf_counter() - start
    stages = {"extraction": extracted - start, "matching and verification": matched - extracted,
              "mapping": start + seconds - matched}
    if not models:
        return Outcome({}, 0, 0.0, seconds, stage_seconds=stages)
    model = max(models.values(), key=lambda m: m.num_reg_images())
    poses = {}
    for image in model.images.values():
        if image.has_pose:
            cam_from_world = image.cam_from_world()
            poses[image.name] = CameraPose(R=cam_from_world.rotation.matrix(), t=cam_from_world.translation)
    return Outcome(poses, model.num_points3D(), float(model.compute_mean_track_length()), seconds,
                   stage_seconds=stages, focal_px=float(next(iter(model.cameras.values())).params[0]))


def pose_error_cells(outcome: Outcome, truth: dict[str, CameraPose] | None) -> list[str]:
    """Rotation error mean and max (deg), the mean relative rotation error of the pairs (deg; no alignment),
    centre error mean and max, and the cameras over WRONG_DEG."""
    if truth is None or len(outcome.poses) < 3:
        return ["-"] * 6
    names = sorted(outcome.poses)
    estimated, true = [outcome.poses[n] for n in names], [truth[n] for n in names]
    errors = aligned_pose_errors(estimated, true)
    return [f"{errors.rotation_deg.mean():.3f}", f"{errors.rotation_deg.max():.3f}",
            f"{relative_rotation_errors_deg(estimated, true).mean():.4f}",
            f"{errors.center.mean():.4f}", f"{errors.center.max():.4f}",
            str(int((errors.rotation_deg > WRONG_DEG).sum()))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="lego,fountain,herzjesu,unity",
                        help="comma-separated: lego, ring, ring16, darkring, ringN, darkringN (N views), "
                        "box, boxN, boxN_seedS, fountain, herzjesu, unity")
    parser.add_argument("--ring-offset", type=int, default=0,
                        help="ringN, darkringN: start from the offset-th view in azimuth order")
    parser.add_argument("--no-pycolmap", action="store_true", help="ours only")
    parser.add_argument("--max-reprojection-sigmas", type=float, default=None,
                        help="ours: the filter's noise-following limit in sigmas (0: the fixed 4 px limit)")
    parser.add_argument("--workers", type=int, default=0,
                        help="ours: SIFT detection threads and verification processes (0: one per core)")
    parser.add_argument("--estimator", choices=["numpy", "opencv"], default=None,
                        help="ours: whose RANSAC verifies the pairs (default: TwoViewConfig's)")
    parser.add_argument("--seeds", default="0",
                        help="ours: comma-separated RANSAC seeds, a run and a row each (pycolmap runs once)")
    parser.add_argument("--mapper", type=json.loads, default=None,
                        help="ours: MapperConfig fields as JSON (example in the docstring)")
    parser.add_argument("--sift", type=json.loads, default=None,
                        help="ours: SiftConfig fields as JSON, e.g. '{\"max_image_side\": 3200}'")
    parser.add_argument("--uncalibrated", action="store_true",
                        help="lego, fountain, herzjesu without calibration.txt: both methods refine a focal "
                        "length prior (ours: simple-radial; pycolmap: SIMPLE_RADIAL, COLMAP's defaults)")
    parser.add_argument("--repeats", type=int, default=1,
                        help="time ours (first seed) and pycolmap this many times, one after the other: "
                        "the first seed's row gives the median seconds and the median of the paired ratios")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()}")
    header = ("| set | method | registered | rot mean deg | rot max deg | pair rot mean deg | centre mean "
              "| centre max "
              f"| over {WRONG_DEG:g} deg | points | track len | RMS px | Ceres left | seconds "
              "| ours/pycolmap |")
    rows = [header, "|---" * (header.count("|") - 1) + "|"]
    with tempfile.TemporaryDirectory(prefix="bench_sfm_") as tmp:
        work = Path(tmp)
        for key in args.sets.split(","):
            if key == "lego":
                bench = lego_set(work)
            elif key == "ring":
                bench = ground_truth_set(DATA / "lego_ring_400", "lego_ring_400 (50)")
            elif ring := SPARSE_RING.fullmatch(key):
                views = int(ring.group(2)) if ring.group(2) else SPARSE_RING_VIEWS
                bench = sparse_ring_set(work, ring.group(1) is not None, views, args.ring_offset)
            elif box := BOX.fullmatch(key):
                bench = box_ring_set(work, int(box.group(1)) if box.group(1) else BOX_VIEWS,
                                     int(box.group(2) or 0))
            elif key == "fountain":
                bench = strecha_set("fountain-P11", work)
            elif key == "herzjesu":
                bench = strecha_set("Herz-Jesus-P8", work)
            elif key == "unity":
                unity = DATA / "unity_hall"
                bench = BenchSet("unity_hall (match files)", unity, np.loadtxt(unity / "calibration.txt"),
                                 None, features="matches")
            else:
                raise SystemExit(f"unknown set {key!r}")
            if args.uncalibrated and key != "unity":
                bench = uncalibrated_copy(bench, work)
            total = sum(1 for p in bench.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            seeds = [int(seed) for seed in args.seeds.split(",")]
            runs = {seed: run_ours(bench, work / f"ours_{key}_{seed}", args.max_reprojection_sigmas,
                                   args.workers, args.estimator, seed, args.mapper, args.sift)
                    for seed in seeds}
            skip_colmap = args.no_pycolmap or key == "unity"
            theirs = None if skip_colmap else run_pycolmap(bench, work / f"colmap_{key}")
            pairs = [(runs[seeds[0]].seconds, theirs.seconds if theirs else float("nan"))]
            for _ in range(1, args.repeats):
                again = run_ours(bench, work / f"ours_{key}_repeat", args.max_reprojection_sigmas,
                                 args.workers, args.estimator, seeds[0], args.mapper, args.sift)
                pairs.append((again.seconds, float("nan") if skip_colmap
                              else run_pycolmap(bench, work / f"colmap_{key}").seconds))
            if args.repeats > 1:
                ours_seconds, their_seconds = np.array(pairs).T
                print(f"{bench.name}: seconds per repeat, ours {np.round(ours_seconds, 2).tolist()}, "
                      f"pycolmap {np.round(their_seconds, 2).tolist()}, ratios "
                      f"{np.round(ours_seconds / their_seconds, 2).tolist()}", flush=True)
                runs[seeds[0]] = replace(runs[seeds[0]], seconds=float(np.median(ours_seconds)))
                if theirs:
                    theirs = replace(theirs, seconds=float(np.median(their_seconds)))
            paired_ratio = float(np.median([mine / reference for mine, reference in pairs]))
            for seed, ours in runs.items():
                ratio = "-" if theirs is None else (
                    f"{paired_ratio if seed == seeds[0] else ours.seconds / theirs.seconds:.2f}")
                method = "ours" if len(seeds) == 1 else f"ours (seed {seed})"
                rows.append(f"| {bench.name} | {method} | {len(ours.poses)}/{total} | "
                            + " | ".join(pose_error_cells(ours, bench.truth))
                            + f" | {ours.points} | {ours.mean_track_length:.2f} | {ours.rms_px:.3f} | "
                            f"{100 * ours.ceres_left:.3f} % | {ours.seconds:.1f} | {ratio} |")
                print(rows[-1], flush=True)
                stages = ", ".join(f"{stage} {value:.1f}" for stage, value in ours.stage_seconds.items())
                print(f"ours, seconds per stage (detection, matching_and_verification, view_graph: inside "
                      f"features): {stages}; CPU s {ours.cpu_seconds[0]:.2f} + {ours.cpu_seconds[1]:.2f} in "
                      f"worker processes", flush=True)
                loosest = ", ".join(f"{name} {std:.2f}" for name, std in ours.loosest_registrations.items())
                print(f"ours, loosest registrations (rotation std-dev at 1 px, deg): {loosest}", flush=True)
                for warning in ours.fold_warnings:
                    print(f"ours, warning: {warning[:300]}", flush=True)
                print(f"ours, look-alike check: {ours.look_alike_check}", flush=True)
                if ours.conflicts_outcome:
                    print(f"ours, look-alike conflicts: {ours.conflicts_outcome}", flush=True)
            if not bench.calibrated:
                truth_focal = (bench.K[0, 0] + bench.K[1, 1]) / 2
                found = [(method, outcome.focal_px) for method, outcome in
                         (("ours", runs[seeds[0]]), ("pycolmap", theirs)) if outcome is not None]
                print(f"{bench.name}: focal length (truth {truth_focal:.1f} px) " + ", ".join(
                    f"{method} {focal:.1f} px ({100 * (focal / truth_focal - 1):+.2f} %)"
                    for method, focal in found), flush=True)
            if theirs:
                rows.append(f"| {bench.name} | pycolmap | {len(theirs.poses)}/{total} | "
                            + " | ".join(pose_error_cells(theirs, bench.truth))
                            + f" | {theirs.points} | {theirs.mean_track_length:.2f} | - | - | "
                            f"{theirs.seconds:.1f} | |")
                print(rows[-1], flush=True)
                stages = ", ".join(f"{stage} {value:.2f}" for stage, value in theirs.stage_seconds.items())
                print(f"pycolmap, seconds per stage (of its first run): {stages}", flush=True)
    print(f"load average after: {os.getloadavg()}")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
