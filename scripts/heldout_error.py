"""Where a photo run's held-out error lies (benchmarks/RESULTS.md, bench_nerf_real): for each held-out photo,
its PSNR and the share of its squared error in the pixels whose ray direction no training photo's view
contains (content at a distance there was never photographed), the render's mean colour minus the photo's
and the PSNR without it, and the share of its squared error and the PSNR in bands of columns (split at the
fractions of the width --column-splits gives: content at a photo's sides may be in no other photo); what a
perfect field could score: the dominant plane of its rendered surface (a facade), the pixels whose ray meets
that plane where no training photo sees it, and the PSNR with every other pixel exact; how far the rendered
depth is from the reconstruction's at the photo's own sparse points (its depth rays); and the PSNR on random
pixels of each training photo, with the same bias and depth figure.

    python3 scripts/heldout_error.py RUN_DIR RECONSTRUCTION_DIR [--pixels 8192] [--column-splits 0.25,0.9]
        [--plane-tolerance 0.02]

RUN_DIR is a trained run (bench_nerf_real's OUT/SCENE/CONFIG), RECONSTRUCTION_DIR the reconstruction it was
trained on (OUT/sfm/SCENE). Directions and points are compared in the run's scene frame with each training
camera's pinhole view (OpenGL axes: the camera looks down -z, image y up).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from estimation.config import RansacConfig
from estimation.geometry.ransac import ransac
from neural.artefacts import IMAGE_CACHE_DIR
from neural.data import load_dataset_for
from neural.inference import PinholeIntrinsics, load_run, render_frame, render_rays_chunked
from neural.rays import generate_rays, pixel_rays


def inside_view(camera_axes: np.ndarray, dataset) -> np.ndarray:
    """(N,) True where a vector in a camera's axes (N, 3), a direction or a point minus its centre, projects
    into its image: u = fx x / (-z) + cx, v = -fy y / (-z) + cy inside [0, W) x [0, H), z < 0."""
    depth = -camera_axes[:, 2]
    ahead = depth > 1e-9
    u = dataset.fx * camera_axes[:, 0] / np.where(ahead, depth, 1.0) + dataset.cx
    v = -dataset.fy * camera_axes[:, 1] / np.where(ahead, depth, 1.0) + dataset.cy
    return ahead & (u >= 0) & (u < dataset.width) & (v >= 0) & (v < dataset.height)


def seen_by_training(vectors: np.ndarray, dataset, training: np.ndarray, at_infinity: bool) -> np.ndarray:
    """(N,) True where some training camera's view contains the point (N, 3), or with `at_infinity` the unit
    direction, in the scene frame: R^T (X - C), or R^T d, inside its image (occlusion ignored, so a point
    errs towards seen)."""
    seen = np.zeros(len(vectors), bool)
    for index in training:
        pose = dataset.poses[index]
        seen |= inside_view((vectors if at_infinity else vectors - pose[:3, 3]) @ pose[:3, :3], dataset)
    return seen


def planes_through(triples: np.ndarray) -> np.ndarray:
    """(M, 4) planes (n, c), n . X = c with unit n, through point triples (B, 3, 3), less collinear ones."""
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    planar = lengths > 1e-12
    normals = normals[planar] / lengths[planar, None]
    return np.column_stack([normals, np.einsum("md,md->m", normals, triples[planar, 0])])


def plane_distances(planes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, N) |n . X - c| of every point (N, 3) to every plane (M, 4)."""
    return np.abs(points @ planes[:, :3].T - planes[:, 3]).T


def least_squares_plane(points: np.ndarray) -> np.ndarray:
    """(1, 4) the plane through the centroid of points (N, 3) normal to their smallest singular vector."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    return np.append(normal, normal @ centre)[None]


def dominant_plane(points: np.ndarray, tolerance: float) -> tuple[np.ndarray, float]:
    """The plane n . X = c (unit n) that most points (N, 3) lie within `tolerance` of: the project's RANSAC
    over point triples, each new best re-fitted by least squares on its inliers."""
    plane = ransac((points,), planes_through, 3, plane_distances, tolerance, RansacConfig(),
                   refit=least_squares_plane, model_name="plane").model
    return plane[:3], float(plane[3])


def seen_on_plane(origins: np.ndarray, directions: np.ndarray, plane: tuple[np.ndarray, float], dataset,
                  training: np.ndarray) -> np.ndarray:
    """(N,) False where the ray o + t d meets the plane n . X = c ahead (t = (c - n . o) / (n . d) > 0) at a
    point no training photo sees; True elsewhere (a ray that misses the plane is counted as seen)."""
    normal, offset = plane
    facing = directions @ normal
    t = (offset - origins @ normal) / np.where(np.abs(facing) > 1e-12, facing, 1e-12)
    return (t <= 0) | seen_by_training(origins + t[:, None] * directions, dataset, training, False)


def rays_of(dataset, index: int):
    """The rays of every pixel of the dataset's photo `index` (scene frame)."""
    pose = torch.as_tensor(dataset.poses[index], dtype=torch.float32)
    return generate_rays(pose, dataset.width, dataset.height, dataset.fx, dataset.fy, dataset.cx, dataset.cy)


def depth_error(run, dataset, index: int) -> str:
    """' at its N sparse points the rendered depth is X % off the reconstruction's (median)': |rendered -
    reconstructed| / reconstructed distance along the rays of the photo's depth rays (its points)."""
    rays = dataset.depth_rays
    if rays is None or not (rays.image == index).any():
        return ""
    mine = rays.image == index
    pose = torch.as_tensor(dataset.poses[index], dtype=torch.float32)
    u, v = (torch.as_tensor(values[mine], dtype=torch.float32) for values in (rays.u, rays.v))
    ray = pixel_rays(pose, u, v, dataset.fx, dataset.fy, dataset.cx, dataset.cy)
    with torch.no_grad():
        rendered = render_rays_chunked(run.model, ray.origins, ray.directions, run.scene, run.background,
                                       run.config.chunk_rays)
    distance = np.asarray(rays.distance[mine], np.float64)
    relative = np.abs(rendered.depth.numpy() - distance) / distance
    return (f"; at its {mine.sum()} sparse points the rendered depth is {np.median(relative):.1%} off the "
            f"reconstruction's (median)")


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


def perfect_field(error: np.ndarray, seen: np.ndarray, on_plane: float) -> str:
    """What the pixels no training photo sees (`seen` False) cost: their share, their PSNR and the PSNR with
    every other pixel's squared error (`error`, per pixel) at 0."""
    if seen.all():
        return f"its rendered surface's dominant plane holds {on_plane:.0%} of it, all of it seen in training"
    unseen_error = error[~seen]
    return (f"its rendered surface's dominant plane holds {on_plane:.0%} of it, and {1 - seen.mean():.1%} of "
            f"its pixels meet that plane where no training photo sees it "
            f"(PSNR {psnr(unseen_error.mean()):.2f} dB there): with every other pixel exact its PSNR would "
            f"be {psnr(unseen_error.sum() / len(error)):.2f} dB")


def width_fractions(text: str) -> list[float]:
    """--column-splits: increasing fractions of the width strictly between 0 and 1, comma-separated."""
    try:
        fractions = [float(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of numbers") from None
    if any(not 0 < f < 1 for f in fractions) or fractions != sorted(set(fractions)):
        raise argparse.ArgumentTypeError(f"{text!r}: the fractions must increase, strictly between 0 and 1")
    return fractions


def plane_figures(surface: np.ndarray, origins: np.ndarray, directions: np.ndarray, error: np.ndarray,
                  dataset, training: np.ndarray, tolerance: float) -> str:
    """`perfect_field` on the dominant plane of up to 4096 of the rendered surface points (N, 3), the rays
    (origins, directions) of every pixel and their squared errors."""
    if len(surface) < 3:
        return "no rendered surface to fit a plane to"
    rng = np.random.default_rng(0)
    sample = surface[rng.choice(len(surface), min(len(surface), 4096), replace=False)]
    plane = dominant_plane(sample, tolerance)
    on_plane = np.mean(np.abs(sample @ plane[0] - plane[1]) < tolerance)
    return perfect_field(error, seen_on_plane(origins, directions, plane, dataset, training), on_plane)


def positive_distance(text: str) -> float:
    """--plane-tolerance: a finite distance above 0."""
    try:
        distance = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(distance) or distance <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: the tolerance must be a finite distance above 0")
    return distance


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("reconstruction", type=Path)
    parser.add_argument("--pixels", type=int, default=8192, help="random pixels rendered per training photo")
    parser.add_argument("--column-splits", type=width_fractions, default=[0.25, 0.9],
                        help="width fractions where the held-out photos' column bands split (0.25,0.9)")
    parser.add_argument("--plane-tolerance", type=positive_distance, default=0.02,
                        help="distance (scene units, the box spans [-1, 1]) within which rendered surface "
                        "points belong to the dominant plane (0.02)")
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
        rays = rays_of(dataset, index)
        origins = rays.origins.reshape(-1, 3).numpy().astype(np.float64)
        directions = rays.directions.reshape(-1, 3).numpy().astype(np.float64)
        unseen = ~seen_by_training(directions, dataset, training, at_infinity=True)
        bias = difference.reshape(-1, 3).mean(axis=0)
        surface = origins + rendered.depth.numpy().reshape(-1, 1) * directions
        opaque = rendered.opacity.numpy().ravel() > 0.5
        plane = plane_figures(surface[opaque], origins, directions, error, dataset, training,
                              args.plane_tolerance)
        print(f"held-out {Path(dataset.image_names[index]).name}: PSNR {psnr(error.mean()):.2f} dB; "
              f"{unseen.mean():.1%} of its pixels look where no training photo does and carry "
              f"{error[unseen].sum() / error.sum():.1%} of its squared error; render - photo mean colour "
              f"{np.round(bias, 3).tolist()}, PSNR without it {psnr(((difference - bias) ** 2).mean()):.2f} "
              f"dB; squared error by {column_bands(image_error, args.column_splits)}; "
              f"{plane}{depth_error(run, dataset, index)}")
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
              f"on {args.pixels} pixels; render - photo mean colour {bias}{depth_error(run, dataset, index)}")


if __name__ == "__main__":
    main()
