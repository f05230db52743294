"""SIFT features and matches (OpenCV + numpy) merged into multi-view `Tracks`, for folders without match
files.

Detection runs on the image downscaled to `max_image_side` (keypoints mapped back to full-resolution
pixels, OpenCV convention: the centre of the top-left pixel is (0, 0)) and keeps the `max_features`
strongest keypoints; descriptors are RootSIFT (sqrt of the L1-normalized SIFT vector, hence unit L2
norm, so Euclidean distance compares them by the Hellinger kernel). Candidate pairs come from
`features.pairs` (exhaustive, or retrieval + sequence), matches from `features.matching` (ratio test and
mutual check). With a TwoViewConfig every pair is verified geometrically (`two_view.geometry`: E, F and H
in RANSAC and COLMAP's two-view geometry type); the inliers of its model survive. `SiftConfig.workers`
images are detected at once (threads: OpenCV releases the GIL), then as many query images are matched
against their partners and their pairs verified at once, one query image per item (processes,
`estimation.parallel`: the RANSAC loops hold the GIL; this process is one of them); the processes start
(spawn, imports) while the threads detect, and receive every image's descriptors once after. The result does
not depend on the count. The two stages work in chunks of images and blocks of query images
(`extract_chunk`, `match_block`: pure functions) that a `FeatureStages` runs: `PoolStages` on this machine,
or other machines' workers; the chunks' results are gathered here, the same whoever ran them.
The surviving matches are joined into tracks by the image-aware union-find of `track_building`, most
distinctive matches (lowest ratio) first.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from functools import cached_property
from itertools import repeat
from pathlib import Path
from typing import NamedTuple, Protocol, runtime_checkable

import cv2
import numpy as np

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig
from estimation.errors import DegenerateConfigurationError
from estimation.features.matching import (
    EMPTY_MATCHES,
    DescriptorMatches,
    DescriptorSet,
    array_namespace,
    descriptor_set,
    match_one_to_many,
    matching_device,
)
from estimation.features.pairs import candidate_pairs
from estimation.features.track_building import assemble_tracks
from estimation.features.view_graph import NO_LOOK_ALIKES, LookAlikes, look_alikes_under
from estimation.io.images import ImageSet, load_rgb
from estimation.parallel import WorkerPool, resolve_workers
from estimation.two_view.geometry import TwoViewGeometry, estimate_two_view_geometry, verify_epipolar
from estimation.types import ProgressCallback, Tracks

DETECTION_SHARE = 0.4
"""Fraction of the SIFT progress spent detecting (the rest matching and verifying), for the progress bar."""
WORKER_MODULES = ("estimation.features.sift",)
"""What the worker processes import as they start: everything `match_and_verify` needs."""


class ImageFeatures(NamedTuple):
    """Keypoints (N, 2) full-resolution pixel uv, their SIFT descriptors (N, 128) uint8, as OpenCV makes
    them (its float descriptors are these whole numbers), and their sizes (N,): the diameter of each
    keypoint's neighbourhood in full-resolution pixels (OpenCV's size; it grows with the keypoint's scale,
    and so does the error of its position)."""

    uv: np.ndarray
    sift: np.ndarray
    size: np.ndarray

    @property
    def descriptors(self) -> np.ndarray:
        """The RootSIFT descriptors (N, 128) float32, made at each access."""
        return root_sift(self.sift)


@dataclass(frozen=True)
class TrackFeatures:
    """Every image's keypoints and SIFT descriptors, and the keypoint behind each observation of the tracks:
    what guided 2D-3D matching (`estimation.mapper.guided`) compares an image's keypoints with."""

    images: list[ImageFeatures]       # image index -> its keypoints (full-resolution pixels) and SIFT
    observation_keypoint: np.ndarray  # (O,) keypoint index of each track observation in its image

    def observation_sizes(self, obs_images: np.ndarray) -> np.ndarray:
        """(O,) the keypoint size (full-resolution pixels) behind each track observation, seen in
        obs_images (the tracks' image_index)."""
        sizes = np.empty(len(self.observation_keypoint))
        for image in np.unique(obs_images):
            chosen = obs_images == image
            sizes[chosen] = self.images[image].size[self.observation_keypoint[chosen]]
        return sizes

    def observation_descriptors(self, obs_ids: np.ndarray, obs_images: np.ndarray) -> np.ndarray:
        """RootSIFT descriptors (len(obs_ids), 128) of the given track observations, seen in obs_images."""
        keypoints = self.observation_keypoint[obs_ids]
        rows = np.empty((len(obs_ids), self.images[0].sift.shape[1]), np.uint8)
        for image in np.unique(obs_images):
            chosen = obs_images == image
            rows[chosen] = self.images[image].sift[keypoints[chosen]]
        return root_sift(rows)


@dataclass(frozen=True)
class SiftResult:
    """Tracks from SIFT, with the counts that went into them."""

    tracks: Tracks
    keypoints_per_image: list[int]
    matches_per_pair: dict[tuple[int, int], int]        # after the ratio test and mutual check
    verified_per_pair: dict[tuple[int, int], int]       # kept after geometric verification
    num_rejected_links: int
    two_view: dict[tuple[int, int], TwoViewGeometry] = field(default_factory=dict)   # verified pairs
    # detection, matching_and_verification, view_graph
    seconds_per_stage: dict[str, float] = field(default_factory=dict)
    # with defer_planarity: the pixels of the matches (in i, in j) of each pair whose planarity is untested
    untested_uv: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    features: TrackFeatures | None = None   # the keypoints and descriptors behind the tracks
    look_alikes: LookAlikes = NO_LOOK_ALIKES   # the verified pairs left out of the tracks (`view_graph`)
    verified: VerifiedMatches | None = None    # what the tracks were joined from


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT: d' = sqrt(d / ||d||_1), so ||d'||_2 = 1 (Arandjelovic & Zisserman 2012)."""
    descriptors = np.asarray(descriptors, np.float32)
    l1 = np.abs(descriptors).sum(axis=1, keepdims=True)
    return np.sqrt(descriptors / np.maximum(l1, np.finfo(np.float32).tiny))


CONTRAST_WINDOW = 9
"""Side of the neighbourhood whose intensity std tells a textured pixel from a constant region."""
CONTRAST_PREVIEW_SIDE = 800
"""The RMS contrast and the constant regions are measured on the image area-downscaled to this longest side
(the contrast within 0.006 of the full-size value on the Strecha photos, in 3 instead of 140 ms; the
window then spans as much of the scene whatever the resolution)."""
OPENCV_SIFT_OFFSET_PX = 0.25
"""How far OpenCV's SIFT places every keypoint right of and below where it is, in the pixels of the image it
was given: its first octave is that image upscaled 2x by `resize` (pixel x of the upscaled image lies at
x / 2 - 0.25 of the original), but it reports x / 2. Gaussian blobs at known centres come out 0.25 px off in
both axes at every scale; `enable_precise_upscale` removes the offset but changes which keypoints are found
(lego 87-88/90 at 0.45-0.57 deg, RANSAC seeds 0-3)."""


class ImageContrast(NamedTuple):
    """RMS contrast of an image's textured pixels, and where they are."""

    rms: float                 # std of the intensities (0..1) of the textured pixels (0: none)
    textured: np.ndarray       # (H, W) uint8 mask, 255 where the neighbourhood is not constant


def image_contrast(gray: np.ndarray, min_std: float, window: int = CONTRAST_WINDOW) -> ImageContrast:
    """textured = std_{window x window}(I) >= min_std, rms = std(I[textured]) for the uint8 image I / 255."""
    intensity = gray.astype(np.float32) / 255.0
    mean = cv2.blur(intensity, (window, window))
    local_std = np.sqrt(np.maximum(cv2.blur(intensity * intensity, (window, window)) - mean * mean, 0.0))
    textured = local_std >= min_std
    rms = float(intensity[textured].std()) if textured.any() else 0.0
    return ImageContrast(rms, textured.astype(np.uint8) * 255)


def adaptive_contrast_threshold(contrast: float, config: SiftConfig) -> float:
    """contrast_threshold * clip(contrast / reference_contrast, min_contrast_factor, 1) below low_contrast,
    else contrast_threshold: DoG extrema scale with the image's contrast, so a low-contrast image is held to
    the threshold its structure would meet at the reference contrast."""
    if contrast >= config.low_contrast:
        return config.contrast_threshold
    factor = np.clip(contrast / config.reference_contrast, config.min_contrast_factor, 1.0)
    return float(config.contrast_threshold * factor)


def detect_features(rgb: np.ndarray, config: SiftConfig) -> ImageFeatures:
    """SIFT on the (H, W, 3) uint8 image downscaled to config.max_image_side (area averaging), at most
    config.max_features keypoints; uv in full-resolution pixels: u = (u_cv - 0.25 + 0.5) W / W_s - 0.5, u_cv
    OpenCV's keypoint in the downscaled image (`OPENCV_SIFT_OFFSET_PX`). A
    low-contrast image gets a lower contrast threshold (`adaptive_contrast_threshold`) and no keypoints in
    its constant regions."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    height, width = gray.shape
    scale = min(1.0, config.max_image_side / max(height, width))
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    threshold, mask = config.contrast_threshold, None
    if config.low_contrast > 0:
        shrink = min(1.0, CONTRAST_PREVIEW_SIDE / max(gray.shape))
        preview_size = (max(1, round(gray.shape[1] * shrink)), max(1, round(gray.shape[0] * shrink)))
        preview = gray if shrink == 1.0 else cv2.resize(gray, preview_size, interpolation=cv2.INTER_AREA)
        contrast = image_contrast(preview, config.constant_region_std)
        threshold = adaptive_contrast_threshold(contrast.rms, config)
        if threshold < config.contrast_threshold:
            mask = cv2.resize(contrast.textured, gray.shape[::-1], interpolation=cv2.INTER_NEAREST)
    sift = cv2.SIFT_create(nfeatures=config.max_features, contrastThreshold=threshold)
    keypoints, descriptors = sift.detectAndCompute(gray, mask)
    if descriptors is None:
        return ImageFeatures(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), np.zeros(0))
    # OpenCV's nfeatures keeps ties (and extra orientations) at the cut: enforce the budget exactly.
    strongest = np.argsort([-kp.response for kp in keypoints], kind="stable")[: config.max_features]
    keypoints, descriptors = [keypoints[k] for k in strongest], descriptors[strongest]
    uv_small = np.array([kp.pt for kp in keypoints], float).reshape(-1, 2) - OPENCV_SIFT_OFFSET_PX
    to_full = np.array([width / gray.shape[1], height / gray.shape[0]])
    # OpenCV rounds its float descriptors to whole numbers 0-255 (saturate_cast<uchar>): uint8 keeps them.
    size = np.array([kp.size for kp in keypoints], float) * float(np.mean(to_full))
    return ImageFeatures((uv_small + 0.5) * to_full - 0.5, descriptors.astype(np.uint8), size)


DetectedImage = tuple[ImageFeatures, np.ndarray]
"""An image's features and the RGB colour (N, 3) uint8 at each keypoint."""


def _detect_in_file(path: Path, config: SiftConfig) -> DetectedImage:
    """The image's features and the RGB colour at each keypoint."""
    rgb = load_rgb(path)
    features = detect_features(rgb, config)
    return features, sample_colors(rgb, features.uv)


def extract_chunk(paths: Sequence[Path], config: SiftConfig) -> list[DetectedImage]:
    """One chunk of the extraction stage: each image's features and keypoint colours, in order."""
    return [_detect_in_file(path, config) for path in paths]


def sample_colors(rgb: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """RGB (N, 3) uint8 at the pixels nearest to uv (N, 2), clamped to the image."""
    height, width = rgb.shape[:2]
    columns = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, width - 1)
    rows = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, height - 1)
    return rgb[rows, columns]


@dataclass(frozen=True)
class PairWork:
    """What matching and verifying an image's pairs needs, sent once to each worker process: every image's
    keypoints and uint8 SIFT descriptors (a quarter of the float RootSIFT's bytes: 3.4 MB on lego), and the
    settings."""

    uv: list[np.ndarray]
    sift: list[np.ndarray]
    ratio: float
    max_distance: float
    device: str                          # "cpu" or "cuda" (`matching_device`)
    two_view: TwoViewConfig | None
    ransac: RansacConfig
    K: np.ndarray | None
    matched: dict[int, list[DescriptorMatches]] | None = None   # per query image, when matched beforehand
    test_planarity: bool = True          # False: `verify_epipolar` only (see sift_tracks' defer_planarity)

    @classmethod
    def of(cls, features: list[ImageFeatures], config: SiftConfig, two_view: TwoViewConfig | None = None,
           ransac: RansacConfig = RansacConfig(), K: np.ndarray | None = None, test_planarity: bool = True
           ) -> PairWork:
        """The work of the detected `features` with `config`'s matching settings (`matching_device`)."""
        return cls([f.uv for f in features], [f.sift for f in features], config.ratio, config.max_distance,
                   matching_device(config.device), two_view, ransac, K, test_planarity=test_planarity)

    @cached_property
    def descriptors(self) -> list[DescriptorSet]:
        """Every image's RootSIFT descriptors (`descriptor_set`), made in each process that matches."""
        return [descriptor_set(root_sift(sift)) for sift in self.sift]

    def __getstate__(self) -> dict:
        """What a worker process receives: never the float descriptors made here (4x the uint8 bytes)."""
        return {name: value for name, value in self.__dict__.items() if name != "descriptors"}


def query_matches(work: PairWork, i: int, partners: list[int]) -> list[DescriptorMatches]:
    """Image i's matches with each partner j (`match_one_to_many` on `work.device`)."""
    return match_one_to_many(work.descriptors[i], [work.descriptors[j] for j in partners], work.ratio,
                             work.max_distance, array_namespace(work.device))


def match_and_verify(work: PairWork, i: int, partners: list[int]
                     ) -> list[tuple[DescriptorMatches, TwoViewGeometry | None]]:
    """Image i's matches with each partner j (`work.matched`'s, else `query_matches`) and, with
    `work.two_view`, the two-view geometry of each pair with at least min_inliers matches (None for the
    others; its planarity untested unless `work.test_planarity`). Only the type and the inliers are used
    (the initial pair's E is estimated and polished again by the mapper): E is not polished here."""
    matches = work.matched[i] if work.matched is not None else query_matches(work, i, partners)
    if work.two_view is None:
        return [(pair_matches, None) for pair_matches in matches]
    verify = estimate_two_view_geometry if work.test_planarity else verify_epipolar
    return [(pair_matches, verify(
                work.uv[i][pair_matches.index_a], work.uv[j][pair_matches.index_b], K1=work.K, K2=work.K,
                config=work.two_view, ransac=work.ransac, refine_essential=False)
             if len(pair_matches.ratio) >= work.two_view.min_inliers else None)
            for j, pair_matches in zip(partners, matches, strict=True)]


Pair = tuple[int, int]
Query = tuple[int, list[int]]
"""A query image i and its partners j: the pairs (i, j) matched together (i's descriptors searched once)."""
PairOutcome = tuple[DescriptorMatches, TwoViewGeometry | None]
"""A pair's matches and, when verified, its two-view geometry (`match_and_verify`)."""


def match_block(work: PairWork, block: Sequence[Query]) -> list[list[PairOutcome]]:
    """One block of the matching stage: each query image's outcomes with its partners (`match_and_verify`)."""
    return [match_and_verify(work, i, partners) for i, partners in block]


def image_chunks(paths: Sequence[Path], images_per_chunk: int) -> list[list[Path]]:
    """The extraction stage's chunks: consecutive runs of at most `images_per_chunk` images."""
    return [list(paths[k:k + images_per_chunk]) for k in range(0, len(paths), images_per_chunk)]


def pair_blocks(queries: Sequence[Query], pairs_per_block: int) -> list[list[Query]]:
    """The matching stage's blocks: consecutive queries, each block closed once it holds `pairs_per_block`
    pairs (a query is never split: its descriptors are searched once)."""
    blocks: list[list[Query]] = []
    size = pairs_per_block
    for query in queries:
        if size >= pairs_per_block:
            blocks.append([])
            size = 0
        blocks[-1].append(query)
        size += len(query[1])
    return blocks


@runtime_checkable
class FeatureStages(Protocol):
    """Where the two chunked stages of `sift_tracks` run: `extract` maps `extract_chunk` over image chunks
    and `match` maps `match_block` over pair blocks, each yielding the results in order as they are done.
    The chunks, the blocks and the gathering of their results are `sift_tracks`' own, so the result does not
    depend on where they ran."""

    images_per_chunk: int
    pairs_per_block: int

    def extract(self, chunks: list[list[Path]], config: SiftConfig) -> Iterator[list[DetectedImage]]: ...

    def match(self, work: PairWork, blocks: list[list[Query]]) -> Iterator[list[list[PairOutcome]]]: ...


class PoolStages:
    """The stages in this machine: one image per chunk on `workers` threads (OpenCV and the image decoders
    release the GIL), one query image per block in the `pool`'s processes (`work` becomes its context)."""

    images_per_chunk = 1
    pairs_per_block = 1

    def __init__(self, pool: WorkerPool, workers: int) -> None:
        self.pool = pool
        self.workers = workers

    def extract(self, chunks: list[list[Path]], config: SiftConfig) -> Iterator[list[DetectedImage]]:
        with ThreadPoolExecutor(self.workers) as threads:
            yield from threads.map(extract_chunk, chunks, repeat(config))

    def match(self, work: PairWork, blocks: list[list[Query]]) -> Iterator[list[list[PairOutcome]]]:
        self.pool.share(work)
        return self.pool.map(match_block, blocks)


def sift_pool(config: SiftConfig) -> WorkerPool:
    """The worker processes of `sift_tracks` (config.workers, this process one of them), started now; the
    caller shuts them down."""
    return WorkerPool(resolve_workers(config.workers), modules=WORKER_MODULES, caller_works=True)


def match_and_verify_pairs(work: PairWork, pairs: list[Pair], pool: WorkerPool,
                           progress: Callable[[float], None] = lambda fraction: None,
                           stages: FeatureStages | None = None,
                           ) -> tuple[dict[Pair, DescriptorMatches], dict[Pair, TwoViewGeometry]]:
    """The matches of every pair (i, j) and the geometry of each pair verified (`match_and_verify`), in
    blocks of query images with all their partners (`pair_blocks`), run by `stages` (default: `PoolStages`
    in the `pool`, `WORKER_MODULES` imported); `progress` gets the fraction of the work done."""
    stages = stages or PoolStages(pool, pool.workers)
    partners_of: dict[int, list[int]] = defaultdict(list)
    for i, j in pairs:
        partners_of[i].append(j)
    # Largest first (the product's work: query rows times partner rows), so that the last items to finish
    # are small and no process waits long for another.
    cost = {i: len(work.uv[i]) * sum(len(work.uv[j]) for j in partners)
            for i, partners in partners_of.items()}
    queries = sorted(partners_of, key=lambda i: -cost[i])
    if work.device != "cpu":
        # A GPU matches in this process (one device context, not one per worker process); the workers
        # only verify.
        work = replace(work, sift=[], matched={i: query_matches(work, i, partners_of[i])
                                                      for i in queries})
    matches: dict[Pair, DescriptorMatches] = {}
    geometries: dict[Pair, TwoViewGeometry] = {}
    done, total = 0, max(1, sum(cost.values()))
    blocks = pair_blocks([(i, partners_of[i]) for i in queries], stages.pairs_per_block)
    for block, block_outcomes in zip(blocks, stages.match(work, blocks), strict=True):
        for (i, partners), image_outcomes in zip(block, block_outcomes, strict=True):
            for j, (pair_matches, geometry) in zip(partners, image_outcomes, strict=True):
                matches[(i, j)] = pair_matches
                if geometry is not None:
                    geometries[(i, j)] = geometry
            done += cost[i]
        progress(done / total)
    return matches, geometries


@dataclass(frozen=True)
class VerifiedMatches:
    """Every image's keypoints and colours and each matched pair's matches that verification kept (all of
    them without verification): what the tracks are joined from (`joined_tracks`), and the inliers whose
    rotations the look-alike checks take (`inlier_uv`: `view_graph.look_alikes_under`)."""

    image_names: list[str]
    uv: list[np.ndarray]                       # image index -> keypoints (N, 2) full-resolution pixels
    colors: list[np.ndarray]                   # image index -> their RGB (N, 3)
    matches: dict[Pair, DescriptorMatches]     # every matched pair (i, j), i < j: its kept matches

    def inlier_uv(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """The pixels of pair (i, j)'s kept matches in i and in j."""
        pair_matches = self.matches[(i, j)]
        return self.uv[i][pair_matches.index_a], self.uv[j][pair_matches.index_b]

    def per_pair(self) -> dict[Pair, int]:
        """How many matches each pair kept."""
        return {pair: len(pair_matches.ratio) for pair, pair_matches in self.matches.items()}

    def without(self, pairs: Sequence[Pair]) -> VerifiedMatches:
        """These matches with none kept for `pairs`."""
        left_out = set(pairs)
        return replace(self, matches={pair: EMPTY_MATCHES if pair in left_out else pair_matches
                                      for pair, pair_matches in self.matches.items()})


class JoinedTracks(NamedTuple):
    """Tracks joined from pairwise matches, and the keypoint behind each of their observations."""

    tracks: Tracks
    observation_keypoint: np.ndarray   # (O,) keypoint index of each observation in its image
    num_rejected_links: int            # matches that would have put an image twice into a track


def joined_tracks(verified: VerifiedMatches) -> JoinedTracks:
    """The kept matches joined into tracks by `assemble_tracks`, the most distinctive (lowest ratio) first;
    only keypoints that take part in a match become nodes."""
    offsets = np.concatenate([[0], np.cumsum([len(uv) for uv in verified.uv])])
    links = [np.stack([offsets[i] + pair_matches.index_a, offsets[j] + pair_matches.index_b], axis=1)
             for (i, j), pair_matches in verified.matches.items()]
    all_links = np.concatenate(links).reshape(-1, 2) if links else np.zeros((0, 2), np.int64)
    ratios = np.concatenate([pair_matches.ratio for pair_matches in verified.matches.values()] or [[]])
    all_links = all_links[np.argsort(ratios, kind="stable")]
    used_nodes, compact_links = np.unique(all_links, return_inverse=True)
    node_image = np.searchsorted(offsets, used_nodes, side="right") - 1
    assembly = assemble_tracks(verified.image_names, node_image, np.concatenate(verified.uv)[used_nodes],
                               np.concatenate(verified.colors)[used_nodes], compact_links.reshape(-1, 2))
    return JoinedTracks(assembly.tracks,
                        used_nodes[assembly.observation_node] - offsets[assembly.tracks.image_index],
                        assembly.num_rejected_links)


def sift_tracks(
    images: ImageSet,
    config: SiftConfig,
    two_view: TwoViewConfig | None = None,
    ransac: RansacConfig = RansacConfig(),
    K: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    pool: WorkerPool | None = None,
    defer_planarity: bool = False,
    stages: FeatureStages | None = None,
    alternative: int | None = None,
) -> SiftResult:
    """Detect, choose pairs, match (and with `two_view`, verify: E with K, else F; H for the type), and
    merge the matches into tracks. `progress(stage, fraction)` gets this step's own fraction 0..1.
    `pool`: the worker processes to use (a `sift_pool`, left running; default: one of this call's own).
    `defer_planarity`: H is left out (the tracks do not depend on it); `untested_uv` holds what
    `features.planarity` needs to test it later. `stages`: where the extraction chunks and the matching
    blocks run (default: `PoolStages`, this machine's threads and the pool's processes). With `two_view` and
    K, the look-alike pairs are left out of the tracks (`features.view_graph`); where the strongest pairs
    conflict, none is, or with `alternative` k, the k-th alternative's (`LookAlikes.alternatives`)."""
    report = progress or (lambda stage, fraction: None)
    workers = resolve_workers(config.workers)
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    # The processes start (spawn, imports) while the threads detect; they get the descriptors after. A given
    # pool keeps running after this call, a pool of its own is shut down.
    with nullcontext(pool) if pool is not None else sift_pool(config) as pool:
        stages = stages or PoolStages(pool, workers)
        detected: list[DetectedImage] = []
        for chunk_features in stages.extract(image_chunks(images.paths, stages.images_per_chunk), config):
            detected.extend(chunk_features)
            report("features", DETECTION_SHARE * len(detected) / len(images))
        features, colors = [f for f, _ in detected], [c for _, c in detected]
        seconds["detection"] = time.perf_counter() - started

        started = time.perf_counter()
        work = PairWork.of(features, config, two_view, ransac, K, test_planarity=not defer_planarity)
        # This process matches too (the pool's caller works): its RootSIFT sets serve both.
        pairs = candidate_pairs(images.names, [d.descriptors for d in work.descriptors], config)
        matches, geometries = match_and_verify_pairs(work, pairs, pool, lambda fraction: report(
            "matching", DETECTION_SHARE + (1 - DETECTION_SHARE) * fraction), stages)
        seconds["matching_and_verification"] = time.perf_counter() - started

    # A pair that was not verified (too few matches) keeps none.
    verified = VerifiedMatches(images.names, work.uv, colors, {
        pair: DescriptorMatches(*(array[geometries[pair].inlier_mask] for array in matches[pair]))
        if pair in geometries else EMPTY_MATCHES if two_view is not None else matches[pair]
        for pair in pairs})
    look_alikes = NO_LOOK_ALIKES
    # Only with K: under a focal length prior the pairs' rotations were too rough to tell look-alikes (a
    # rendered box's strongest pairs conflicted, and lego_ring_400 lost accuracy); without it the pipeline
    # checks under a folded model's refined K instead.
    if two_view is not None and K is not None:
        started = time.perf_counter()
        _, look_alikes = look_alikes_under(K, geometries, verified.inlier_uv, len(images), two_view)
        if alternative is not None and look_alikes.conflicts:
            look_alikes = look_alikes._replace(pairs=list(look_alikes.alternatives[alternative]))
        # Left out of the geometries, a look-alike neither links tracks nor votes on registrations.
        verified = verified.without(look_alikes.pairs)
        left_out = set(look_alikes.pairs)
        geometries = {pair: geometry for pair, geometry in geometries.items() if pair not in left_out}
        seconds["view_graph"] = time.perf_counter() - started
    if not any(verified.per_pair().values()):
        raise DegenerateConfigurationError(f"{images.folder}: SIFT found no matches between any two images")
    joined = joined_tracks(verified)
    return SiftResult(
        tracks=joined.tracks,
        keypoints_per_image=[len(f.uv) for f in features],
        matches_per_pair={pair: len(m.ratio) for pair, m in matches.items()},
        verified_per_pair=verified.per_pair(),
        num_rejected_links=joined.num_rejected_links,
        two_view=geometries,
        seconds_per_stage=seconds,
        untested_uv={(i, j): (work.uv[i][matches[(i, j)].index_a], work.uv[j][matches[(i, j)].index_b])
                     for (i, j), geometry in geometries.items() if not geometry.planarity_tested},
        features=TrackFeatures(features, joined.observation_keypoint),
        look_alikes=look_alikes,
        verified=verified,
    )
