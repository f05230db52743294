"""PNG figures of a reconstruction (matplotlib, Agg; no global pyplot state).

- the initial pair: putative matches and the RANSAC inliers drawn over the two images;
- the initial pair's points from linear (DLT) and non-linear triangulation, from above;
- all registered cameras and points, from above.

"From above" is the world's x-z plane seen from -y: the world frame is the initial pair's first
camera (OpenCV axes, y down), so its forward axis +z points up the page and +x to the right.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from estimation.types import CameraPose

DPI = 120
PNG_COMPRESS_LEVEL = 1
"""Fast zlib level: the photo figures encode several times faster, for slightly larger files."""
VIEW_PERCENTILES = (1.0, 99.0)
"""The top views frame the points between these percentiles (a few far outliers would squash the rest)."""
VIEW_MARGIN = 0.1
MAX_DRAWN_MATCHES = 400
"""Draw at most this many match lines per panel (a random subset), so the figure stays readable."""
INLIER_COLOR, OUTLIER_COLOR = "#1a9850", "#d73027"


def _save(figure: Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(figure)
    figure.savefig(path, dpi=DPI, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    return path


def _subset(count: int, limit: int, seed: int = 0) -> np.ndarray:
    if count <= limit:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=limit, replace=False))


def _view_limits(xy: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    low, high = np.percentile(xy, VIEW_PERCENTILES, axis=0)
    span = np.maximum(high - low, 1e-9)
    low, high = low - VIEW_MARGIN * span, high + VIEW_MARGIN * span
    return (float(low[0]), float(high[0])), (float(low[1]), float(high[1]))


def plot_pair_matches(
    rgb_a: np.ndarray,
    rgb_b: np.ndarray,
    uv_a: np.ndarray,
    uv_b: np.ndarray,
    inlier_mask: np.ndarray,
    names: tuple[str, str],
    path: Path,
) -> Path:
    """Two panels over the side-by-side images: all putative matches, then the RANSAC inliers only."""
    inlier_mask = np.asarray(inlier_mask, bool)
    width_a = rgb_a.shape[1]
    canvas = np.zeros((max(rgb_a.shape[0], rgb_b.shape[0]), width_a + rgb_b.shape[1], 3), np.uint8)
    canvas[: rgb_a.shape[0], :width_a] = rgb_a
    canvas[: rgb_b.shape[0], width_a:] = rgb_b
    figure = Figure(figsize=(12, 9.5))
    figure.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.95, hspace=0.12)
    panels = [
        ("putative matches", np.ones_like(inlier_mask)),
        ("RANSAC inliers", inlier_mask),
    ]
    for row, (title, shown) in enumerate(panels):
        axes = figure.add_subplot(2, 1, row + 1)
        axes.imshow(canvas)
        chosen = np.flatnonzero(shown)[_subset(int(shown.sum()), MAX_DRAWN_MATCHES)]
        segments = np.stack([uv_a[chosen], uv_b[chosen] + [width_a, 0.0]], axis=1)
        colors = np.where(inlier_mask[chosen], INLIER_COLOR, OUTLIER_COLOR)
        axes.add_collection(LineCollection(segments, colors=list(colors), linewidths=0.6, alpha=0.8))
        axes.scatter(*uv_a[chosen].T, s=3, c=list(colors))
        axes.scatter(*(uv_b[chosen] + [width_a, 0.0]).T, s=3, c=list(colors))
        axes.set_title(
            f"{names[0]} | {names[1]}: {title} ({int(shown.sum())} of {inlier_mask.size}; "
            f"{int(inlier_mask.sum())} inliers in green, outliers in red)"
        )
        axes.set_axis_off()
    return _save(figure, path)


def plot_triangulation_comparison(
    points_linear: np.ndarray, points_nonlinear: np.ndarray, path: Path
) -> Path:
    """Top view of the linear (DLT) and non-linear points, and how far non-linear refinement moved them."""
    points_linear = np.asarray(points_linear, float).reshape(-1, 3)
    points_nonlinear = np.asarray(points_nonlinear, float).reshape(-1, 3)
    figure = Figure(figsize=(13, 5.5), layout="constrained")
    top = figure.add_subplot(1, 2, 1)
    for points, color, label in ((points_linear, "#4575b4", "linear (DLT)"),
                                 (points_nonlinear, "#f46d43", "non-linear")):
        top.scatter(points[:, 0], points[:, 2], s=6, c=color, label=label, alpha=0.7)
    moves = np.stack([points_linear[:, [0, 2]], points_nonlinear[:, [0, 2]]], axis=1)
    top.add_collection(LineCollection(moves, colors="grey", linewidths=0.5))
    if len(points_linear):
        x_limits, z_limits = _view_limits(np.vstack([points_linear, points_nonlinear])[:, [0, 2]])
        top.set_xlim(*x_limits)
        top.set_ylim(*z_limits)
    top.set_xlabel("x")
    top.set_ylabel("z (first camera's forward)")
    top.set_title("initial pair, seen from above")
    top.legend(loc="best")
    shift = np.linalg.norm(points_nonlinear - points_linear, axis=1)
    histogram = figure.add_subplot(1, 2, 2)
    upper = float(np.percentile(shift, VIEW_PERCENTILES[1])) if shift.size else 1.0
    histogram.hist(shift, bins=40, range=(0.0, max(upper, 1e-12)), color="#636363")
    median = float(np.median(shift)) if shift.size else 0.0
    beyond = int(np.sum(shift > upper))
    histogram.set_title(f"distance moved by non-linear refinement (median {median:.3g}; "
                        f"{beyond} beyond the axis)")
    histogram.set_xlabel("|X_nonlinear - X_linear| (world units)")
    histogram.set_ylabel("points")
    return _save(figure, path)


def plot_top_view(
    poses: Mapping[int, CameraPose],
    points: np.ndarray,
    colors: np.ndarray,
    image_names: Sequence[str],
    path: Path,
) -> Path:
    """All registered cameras (centre and viewing direction) and points, in the x-z plane."""
    points = np.asarray(points, float).reshape(-1, 3)
    centers = np.array([poses[i].center for i in sorted(poses)]).reshape(-1, 3)
    forwards = np.array([poses[i].R[2] for i in sorted(poses)]).reshape(-1, 3)   # camera z axis in world
    figure = Figure(figsize=(8, 8), layout="constrained")
    axes = figure.add_subplot(1, 1, 1)
    axes.scatter(points[:, 0], points[:, 2], s=2, c=np.asarray(colors, float).reshape(-1, 3) / 255.0)
    x_limits, z_limits = _view_limits(points[:, [0, 2]]) if len(points) else ((0.0, 0.0), (0.0, 0.0))
    # Always show every camera, with a margin, even when the points lie far from them.
    low = np.minimum([x_limits[0], z_limits[0]], centers[:, [0, 2]].min(axis=0))
    high = np.maximum([x_limits[1], z_limits[1]], centers[:, [0, 2]].max(axis=0))
    margin = VIEW_MARGIN * np.maximum(high - low, 1e-9)
    low, high = low - margin, high + margin
    arrow = 0.06 * float(np.max(high - low))
    for index, center, forward in zip(sorted(poses), centers, forwards, strict=True):
        direction = forward[[0, 2]] / max(np.linalg.norm(forward[[0, 2]]), 1e-12)
        axes.annotate("", xy=center[[0, 2]] + arrow * direction, xytext=center[[0, 2]],
                      arrowprops={"arrowstyle": "->", "color": "black"})
        axes.plot(*center[[0, 2]], "k^", markersize=7)
        axes.text(center[0], center[2], f" {image_names[index]}", fontsize=9)
    axes.set_xlim(low[0], high[0])
    axes.set_ylim(low[1], high[1])
    axes.set_aspect("equal", adjustable="box")
    axes.set_xlabel("x")
    axes.set_ylabel("z (first camera's forward)")
    axes.set_title(f"{len(poses)} cameras and {len(points)} points, seen from above")
    return _save(figure, path)


def plot_checkerboard_corners(
    images: Sequence[np.ndarray],
    corners: Sequence[np.ndarray | None],
    titles: Sequence[str],
    path: Path,
    columns: int = 4,
) -> Path:
    """Each photo with its detected board corners (first corner marked), or 'not found', in a grid."""
    rows = max(1, -(-len(images) // columns))
    height, width = images[0].shape[:2]
    figure = Figure(figsize=(3.2 * columns, 3.2 * rows * height / width + 0.4 * rows))
    for k, (rgb, uv, title) in enumerate(zip(images, corners, titles, strict=True)):
        axes = figure.add_subplot(rows, columns, k + 1)
        axes.imshow(rgb)
        if uv is not None:
            axes.plot(uv[:, 0], uv[:, 1], "-", color="#fee08b", linewidth=0.6)
            axes.scatter(uv[:, 0], uv[:, 1], s=4, c=INLIER_COLOR)
            axes.scatter(uv[:1, 0], uv[:1, 1], s=20, c=OUTLIER_COLOR)
        axes.set_title(title, fontsize=8, color="black" if uv is not None else OUTLIER_COLOR)
        axes.set_axis_off()
    figure.tight_layout()
    return _save(figure, path)
