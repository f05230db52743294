"""SIFT features and matches (OpenCV) merged into multi-view `Tracks`, for folders without match files.

Each pair of images is matched with Lowe's ratio test and a mutual (cross) check; all pairs are
matched for small sets, each image with its next `window` images for long sequences. With a
RansacConfig, each pair's matches are then verified geometrically (RANSAC fundamental matrix, a loose
threshold: this only keeps wrong matches from chaining separate points into one track; the pipeline
estimates the pair geometry itself). The surviving matches are joined into tracks by the image-aware
union-find of `track_building`, most distinctive matches (lowest ratio) first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from estimation.config import RansacConfig, SiftConfig
from estimation.errors import DegenerateConfigurationError
from estimation.features.track_building import assemble_tracks
from estimation.io.images import ImageSet, load_rgb
from estimation.two_view.fundamental import ransac_fundamental
from estimation.types import ProgressCallback, Tracks

DETECTION_SHARE = 0.4
"""Fraction of the SIFT progress spent detecting (the rest matching), for the progress bar."""
TWO_VIEW_THRESHOLD_PX = 4.0
"""Sampson distance for the pairwise verification (COLMAP's two-view default); loose on purpose."""
MIN_VERIFIED_MATCHES = 15
"""A pair with fewer matches (before or after verification) contributes none: too few to trust."""


class ImageFeatures(NamedTuple):
    """Keypoints (N, 2) pixel uv and their SIFT descriptors (N, 128) float32."""

    uv: np.ndarray
    descriptors: np.ndarray


class DescriptorMatches(NamedTuple):
    """Matches a[index_a[k]] <-> b[index_b[k]] with Lowe's ratio d1/d2 of each (lower = more distinctive)."""

    index_a: np.ndarray
    index_b: np.ndarray
    ratio: np.ndarray


@dataclass(frozen=True)
class SiftResult:
    """Tracks from SIFT, with the counts that went into them."""

    tracks: Tracks
    keypoints_per_image: list[int]
    matches_per_pair: dict[tuple[int, int], int]        # after the ratio test and mutual check
    verified_per_pair: dict[tuple[int, int], int]       # kept after geometric verification
    num_rejected_links: int


def detect_features(rgb: np.ndarray, max_features: int) -> ImageFeatures:
    """SIFT keypoints and descriptors of an (H, W, 3) uint8 image, at most `max_features` of them."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    keypoints, descriptors = cv2.SIFT_create(nfeatures=max_features).detectAndCompute(gray, None)
    if descriptors is None:
        return ImageFeatures(np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    return ImageFeatures(np.array([kp.pt for kp in keypoints], float).reshape(-1, 2), descriptors)


def match_descriptors(
    descriptors_a: np.ndarray, descriptors_b: np.ndarray, ratio: float
) -> DescriptorMatches:
    """Nearest neighbours a -> b passing d1 < ratio * d2 whose b -> a nearest neighbour is the same a."""
    empty = DescriptorMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(descriptors_a) < 2 or len(descriptors_b) < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(descriptors_a, descriptors_b, k=2)
    backward = matcher.match(descriptors_b, descriptors_a)
    nearest_a_of_b = np.full(len(descriptors_b), -1, np.int64)
    for match in backward:
        nearest_a_of_b[match.queryIdx] = match.trainIdx
    index_a, index_b, ratios = [], [], []
    for candidates in forward:
        if len(candidates) < 2:
            continue
        best, second = candidates
        if best.distance < ratio * second.distance and nearest_a_of_b[best.trainIdx] == best.queryIdx:
            index_a.append(best.queryIdx)
            index_b.append(best.trainIdx)
            ratios.append(best.distance / max(second.distance, np.finfo(float).tiny))
    if not index_a:
        return empty
    return DescriptorMatches(np.array(index_a, np.int64), np.array(index_b, np.int64), np.array(ratios))


def candidate_pairs(num_images: int, config: SiftConfig) -> list[tuple[int, int]]:
    """All pairs up to `exhaustive_up_to` images; otherwise each image with its next `window` images."""
    if num_images <= config.exhaustive_up_to:
        return [(i, j) for i in range(num_images) for j in range(i + 1, num_images)]
    return [(i, j) for i in range(num_images) for j in range(i + 1, min(i + 1 + config.window, num_images))]


def verify_matches(
    uv_a: np.ndarray, uv_b: np.ndarray, matches: DescriptorMatches, ransac: RansacConfig
) -> DescriptorMatches:
    """The matches consistent with one fundamental matrix (Sampson distance < TWO_VIEW_THRESHOLD_PX);
    none if fewer than MIN_VERIFIED_MATCHES remain or no F is found."""
    none = DescriptorMatches(*(array[:0] for array in matches))
    if len(matches.ratio) < MIN_VERIFIED_MATCHES:
        return none
    config = ransac.model_copy(update={"threshold_px": TWO_VIEW_THRESHOLD_PX})
    try:
        inliers = ransac_fundamental(uv_a[matches.index_a], uv_b[matches.index_b], config).inlier_mask
    except DegenerateConfigurationError:
        return none
    if inliers.sum() < MIN_VERIFIED_MATCHES:
        return none
    return DescriptorMatches(*(array[inliers] for array in matches))


def sample_colors(rgb: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """RGB (N, 3) uint8 at the pixels nearest to uv (N, 2), clamped to the image."""
    height, width = rgb.shape[:2]
    columns = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, width - 1)
    rows = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, height - 1)
    return rgb[rows, columns]


def sift_tracks(
    images: ImageSet,
    config: SiftConfig,
    ransac: RansacConfig | None = None,
    progress: ProgressCallback | None = None,
) -> SiftResult:
    """Detect, match (and with `ransac`, verify) the candidate pairs, merge the matches into tracks.

    `progress(stage, fraction)` gets this step's own fraction 0..1.
    """
    report = progress or (lambda stage, fraction: None)
    features, colors = [], []
    for index, path in enumerate(images.paths):
        rgb = load_rgb(path)
        image_features = detect_features(rgb, config.max_features)
        features.append(image_features)
        colors.append(sample_colors(rgb, image_features.uv))
        report("features", DETECTION_SHARE * (index + 1) / len(images))

    offsets = np.concatenate([[0], np.cumsum([len(f.uv) for f in features])])
    pairs = candidate_pairs(len(images), config)
    links, link_ratios, matches_per_pair, verified_per_pair = [], [], {}, {}
    for count, (i, j) in enumerate(pairs, start=1):
        matches = match_descriptors(features[i].descriptors, features[j].descriptors, config.ratio)
        matches_per_pair[(i, j)] = len(matches.ratio)
        if ransac is not None:
            matches = verify_matches(features[i].uv, features[j].uv, matches, ransac)
        verified_per_pair[(i, j)] = len(matches.ratio)
        links.append(np.stack([offsets[i] + matches.index_a, offsets[j] + matches.index_b], axis=1))
        link_ratios.append(matches.ratio)
        report("matching", DETECTION_SHARE + (1 - DETECTION_SHARE) * count / len(pairs))
    all_links = np.concatenate(links).reshape(-1, 2) if links else np.zeros((0, 2), np.int64)
    if len(all_links) == 0:
        raise DegenerateConfigurationError(f"{images.folder}: SIFT found no matches between any two images")
    all_links = all_links[np.argsort(np.concatenate(link_ratios), kind="stable")]

    # Only keypoints that take part in a match become nodes of the track graph.
    used_nodes, compact_links = np.unique(all_links, return_inverse=True)
    node_image = np.searchsorted(offsets, used_nodes, side="right") - 1
    all_uv = np.concatenate([f.uv for f in features])
    all_colors = np.concatenate(colors)
    assembly = assemble_tracks(
        images.names, node_image, all_uv[used_nodes], all_colors[used_nodes], compact_links.reshape(-1, 2)
    )
    return SiftResult(
        tracks=assembly.tracks,
        keypoints_per_image=[len(f.uv) for f in features],
        matches_per_pair=matches_per_pair,
        verified_per_pair=verified_per_pair,
        num_rejected_links=assembly.num_rejected_links,
    )
