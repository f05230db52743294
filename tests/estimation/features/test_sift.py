"""SIFT features: RootSIFT, detection downscaled with keypoints mapped back, the feature budget, and
tracks that agree with known geometry."""

from __future__ import annotations

import multiprocessing
import os
import pickle
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from estimation.config import RansacConfig, SiftConfig, TwoViewConfig
from estimation.errors import InputError
from estimation.features.matching import DescriptorMatches, match_descriptors
from estimation.features.sift import (
    OPENCV_SIFT_OFFSET_PX,
    FeatureStages,
    VerifiedMatches,
    adaptive_contrast_threshold,
    detect_features,
    extract_chunk,
    image_contrast,
    joined_tracks,
    match_block,
    root_sift,
    sample_colors,
    sift_tracks,
)
from estimation.io.images import find_calibration, list_images, load_rgb
from estimation.io.matchfile import load_match_tracks
from estimation.parallel import WorkerPool
from estimation.two_view.geometry import TwoViewGeometryType
from tests.estimation.imports import REPOSITORY


def test_root_sift_is_the_l2_normalized_square_root_of_the_l1_normalized_descriptor():
    raw = np.random.default_rng(0).integers(0, 256, (50, 128)).astype(np.float32)
    descriptors = root_sift(raw)
    np.testing.assert_allclose(np.linalg.norm(descriptors, axis=1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(descriptors**2, raw / raw.sum(axis=1, keepdims=True), rtol=1e-5)
    # Hellinger: the dot product of RootSIFT is the Bhattacharyya coefficient of the L1-normalized SIFT.
    p = raw / raw.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(descriptors[0] @ descriptors[1], np.sqrt(p[0] * p[1]).sum(), rtol=1e-5)


def textured_image(width: int, height: int, seed: int) -> np.ndarray:
    texture = cv2.GaussianBlur(np.random.default_rng(seed).normal(size=(height, width)), (0, 0), 2.5)
    gray = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


def test_keypoints_detected_downscaled_are_mapped_back_to_full_resolution_pixels():
    small = textured_image(240, 180, seed=3)
    large = cv2.resize(small, (720, 540), interpolation=cv2.INTER_CUBIC)    # the same view, 3x the pixels
    reference = detect_features(small, SiftConfig(max_features=400))
    mapped = detect_features(large, SiftConfig(max_features=400, max_image_side=240))
    assert len(mapped.uv) > 100
    assert mapped.uv.max() > 500                                # full-resolution pixel coordinates
    expected = (reference.uv + 0.5) * 3 - 0.5                  # OpenCV convention: pixel centres at integers
    distance = np.linalg.norm(mapped.uv[:, None] - expected[None], axis=2).min(axis=1)
    assert np.median(distance) < 0.5                            # mapping uv * 3 instead would be 1 px off
    assert np.mean(distance < 1.5) > 0.9
    naive = np.linalg.norm(mapped.uv[:, None] - reference.uv[None] * 3, axis=2).min(axis=1)
    assert np.median(naive) > np.median(distance) + 0.5


def blobs_image(centres: np.ndarray, sigma: float, size: int) -> np.ndarray:
    """Gaussian blobs of std-dev sigma at the given (u, v) centres (pixel centres at integers), RGB uint8."""
    v, u = np.mgrid[0:size, 0:size].astype(float)
    blobs = sum(np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2)) for cu, cv in centres)
    gray = np.clip(30 + 200 * blobs, 0, 255).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


@pytest.mark.parametrize("sigma", [1.5, 4.0])
def test_keypoints_of_blobs_lie_at_the_blob_centres_at_every_scale(sigma):
    """OpenCV's SIFT reports its keypoints 0.25 px right of and below where they are (its upscaled first
    octave); detect_features takes that offset off, so a blob's keypoint is found at its centre."""
    centres = np.random.default_rng(1).uniform(30, 370, (30, 2))
    features = detect_features(blobs_image(centres, sigma, 400), SiftConfig())
    distance, nearest = cKDTree(centres).query(features.uv)
    offset = features.uv[distance < 1.5] - centres[nearest[distance < 1.5]]
    assert len(offset) >= 25
    assert np.all(np.abs(np.median(offset, axis=0)) < 0.05)       # OpenCV's own: 0.25 in both axes


def test_keypoint_sizes_are_opencvs_in_full_resolution_pixels():
    """Each keypoint carries its size (the diameter OpenCV gives its neighbourhood, which grows with the
    scale it was found at), mapped to full-resolution pixels like its position."""
    small = textured_image(240, 180, seed=3)
    large = cv2.resize(small, (720, 540), interpolation=cv2.INTER_CUBIC)
    reference = detect_features(small, SiftConfig(max_features=400))
    mapped = detect_features(large, SiftConfig(max_features=400, max_image_side=240))
    opencv = cv2.SIFT_create(contrastThreshold=SiftConfig().contrast_threshold).detect(
        cv2.cvtColor(small, cv2.COLOR_RGB2GRAY), None)
    sizes_at = {}
    for keypoint in opencv:
        sizes_at.setdefault(keypoint.pt, set()).add(keypoint.size)
    assert reference.size.shape == (len(reference.uv),)
    opencv_uv = (reference.uv + OPENCV_SIFT_OFFSET_PX).astype(np.float32)
    assert all(size in sizes_at[tuple(uv)] for uv, size in zip(opencv_uv.tolist(), reference.size.tolist(),
                                                                 strict=True))
    assert reference.size.min() > 1.0 and reference.size.max() > 4 * reference.size.min()  # several octaves
    nearest = cKDTree((reference.uv + 0.5) * 3 - 0.5).query(mapped.uv)[1]
    np.testing.assert_allclose(np.median(mapped.size / reference.size[nearest]), 3.0, rtol=0.05)


def test_a_large_photo_detected_at_half_size_gives_full_size_keypoints_that_match_full_size_detection(
        shared_data):
    """OpenCV's SIFT doubles the image before its first octave, so the image halved samples its finest
    scale on the full-size grid: the keypoints, mapped back to full-size pixels, lie where full-size
    detection puts them and their descriptors match full-size ones at the same place; only the scales
    finer than a full-size pixel (the full size's upsampled octave) are missing. (A fountain-P11 photo
    halved to 1536x1024 stands for the full size, to keep the test short; the default max_image_side halves
    the 3072x2048 original the same way.)"""
    photo = load_rgb(shared_data / "strecha" / "fountain-P11" / "0005.jpg")
    full = cv2.resize(photo, (1536, 1024), interpolation=cv2.INTER_AREA)
    unbounded = 20000                                   # every keypoint of either, no budget cut
    at_full_size = detect_features(full, SiftConfig(max_features=unbounded, max_image_side=1536))
    at_half_size = detect_features(full, SiftConfig(max_features=unbounded, max_image_side=768))
    assert 2000 < len(at_half_size.uv) < len(at_full_size.uv)   # the full size's finest octave is left out
    assert at_half_size.uv.max(axis=0)[0] > 1400                 # full-size pixels
    nearest = cKDTree(at_full_size.uv).query(at_half_size.uv)[0]
    assert np.mean(nearest < 1.0) > 0.75
    assert np.median(nearest) < 0.5
    matches = match_descriptors(at_half_size.descriptors, at_full_size.descriptors, ratio=0.8)
    assert len(matches.ratio) > 0.6 * len(at_half_size.uv)
    offset = np.linalg.norm(at_half_size.uv[matches.index_a] - at_full_size.uv[matches.index_b], axis=1)
    assert np.mean(offset < 1.0) > 0.95


def test_images_up_to_the_default_detection_size_are_detected_at_full_size():
    """The default max_image_side downscales only larger photos: the benchmark's lego (200 px), rings
    (400 px) and Unity Hall (800x600) keep their full-size detection."""
    image = textured_image(800, 600, seed=4)
    assert SiftConfig().max_image_side >= 800
    np.testing.assert_array_equal(detect_features(image, SiftConfig()).uv,
                                  detect_features(image, SiftConfig(max_image_side=3200)).uv)


def test_the_default_contrast_threshold_keeps_opencvs_skip_of_flat_dog_samples():
    """OpenCV refines only DoG extrema with |D| > floor(contrast_threshold / 3 * 0.5 * 255): below 0.02353
    that floor is 0 and every nonzero extremum is refined (1.6x the detection time on lego). The default
    keeps it at 1 and finds a subset of 0.02's keypoints, missing only the weakest few."""
    default = SiftConfig()
    assert np.floor(default.contrast_threshold / 3 * 0.5 * 255) >= 1
    image = textured_image(320, 240, seed=0)
    colmap_like = detect_features(image, SiftConfig(contrast_threshold=0.02)).uv
    keypoints = detect_features(image, default).uv
    assert {tuple(uv) for uv in keypoints} <= {tuple(uv) for uv in colmap_like}
    assert len(keypoints) > 0.95 * len(colmap_like)


def dark_low_contrast_image(width: int = 320, height: int = 240, seed: int = 0) -> np.ndarray:
    """A dark object (a texture of std 6 grey levels around 30) on the right, a constant dark background (12,
    a pixel in 20 off by one level) on the left."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.normal(size=(height, width)), (0, 0), 2.5)
    gray = 30.0 + 6.0 * texture / texture.std()
    speckle = rng.random((height, width // 2)) < 0.05
    gray[:, : width // 2] = 12.0 + rng.integers(-1, 2, (height, width // 2)) * speckle
    gray = np.clip(np.rint(gray), 0, 255).astype(np.uint8)
    return np.repeat(gray[:, :, None], 3, axis=2)


def test_the_contrast_threshold_follows_the_image_contrast_below_the_reference_only():
    config = SiftConfig()
    assert adaptive_contrast_threshold(0.07, config) == config.contrast_threshold
    assert adaptive_contrast_threshold(0.055, config) == pytest.approx(0.22 * config.contrast_threshold)
    assert adaptive_contrast_threshold(0.0, config) == pytest.approx(config.min_contrast_factor
                                                                     * config.contrast_threshold)
    assert adaptive_contrast_threshold(0.0, SiftConfig(low_contrast=0)) == config.contrast_threshold


def test_a_constant_background_is_not_textured_and_the_object_sets_the_contrast():
    image = dark_low_contrast_image()
    contrast = image_contrast(image[:, :, 0], SiftConfig().constant_region_std)
    assert not contrast.textured[:, : 150].any()
    assert (contrast.textured[:, 170:] > 0).mean() > 0.99
    assert 0.005 < contrast.rms < 0.05


def test_a_dark_low_contrast_object_gets_keypoints_and_its_constant_background_none():
    image = dark_low_contrast_image()
    fixed = detect_features(image, SiftConfig(low_contrast=0)).uv
    adaptive = detect_features(image, SiftConfig()).uv
    assert len(adaptive) > 3 * max(len(fixed), 10)
    assert adaptive[:, 0].min() > 150                # none on the background
    photo = textured_image(320, 240, seed=0)         # a well-contrasted image is detected as before
    np.testing.assert_array_equal(detect_features(photo, SiftConfig()).uv,
                                  detect_features(photo, SiftConfig(low_contrast=0)).uv)


def test_the_uint8_descriptors_are_opencvs_float_ones_and_give_their_rootsift_bitwise():
    """The uint8 descriptors (a quarter of the bytes sent to the worker processes) lose nothing: OpenCV's
    float SIFT descriptors are the same whole numbers, so RootSIFT of either is the same to the bit."""
    gray = textured_image(240, 180, seed=5)[:, :, 0]
    config = SiftConfig(max_features=300)
    sift = cv2.SIFT_create(nfeatures=300, contrastThreshold=config.contrast_threshold)
    keypoints, floats = sift.detectAndCompute(gray, None)
    strongest = np.argsort([-kp.response for kp in keypoints], kind="stable")[:300]
    features = detect_features(np.repeat(gray[:, :, None], 3, axis=2), config)
    assert features.sift.dtype == np.uint8 and len(features.sift) > 100
    np.testing.assert_array_equal(features.uv + OPENCV_SIFT_OFFSET_PX,
                                  np.array([keypoints[k].pt for k in strongest]))
    np.testing.assert_array_equal(features.sift, floats[strongest])
    assert features.descriptors.dtype == np.float32
    assert features.descriptors.tobytes() == root_sift(floats[strongest]).tobytes()


def test_the_worker_context_carries_uint8_sift_and_each_process_makes_the_same_rootsift_sets():
    from estimation.features.matching import descriptor_set
    from estimation.features.sift import PairWork

    config = SiftConfig(max_features=200)
    features = [detect_features(textured_image(200, 160, seed), config) for seed in (6, 7)]
    work = pickle.loads(pickle.dumps(PairWork.of(features, config)))    # as a worker receives it
    assert [sift.dtype for sift in work.sift] == [np.uint8, np.uint8]
    for received, image in zip(work.descriptors, features, strict=True):
        assert received.rows.tobytes() == descriptor_set(image.descriptors).rows.tobytes()


def test_the_feature_budget_keeps_the_strongest_keypoints():
    rgb = textured_image(320, 240, seed=4)
    assert len(detect_features(rgb, SiftConfig(max_features=100)).uv) <= 100
    assert len(detect_features(rgb, SiftConfig(max_features=5000)).uv) > 100


def test_matches_between_an_image_and_its_warp_follow_the_homography(shared_data):
    rgb = load_rgb(shared_data / "unity_hall" / "1.png")
    angle, scale = np.deg2rad(10), 0.9
    H = np.array([[scale * np.cos(angle), -scale * np.sin(angle), 60.0],
                  [scale * np.sin(angle), scale * np.cos(angle), -20.0],
                  [2e-5, 1e-5, 1.0]])
    warped = cv2.warpPerspective(rgb, H, (rgb.shape[1], rgb.shape[0]))
    config = SiftConfig(max_features=1500)
    features_a, features_b = detect_features(rgb, config), detect_features(warped, config)
    matches = match_descriptors(features_a.descriptors, features_b.descriptors, ratio=0.8)
    assert len(matches.ratio) >= 200
    mapped = cv2.perspectiveTransform(features_a.uv[matches.index_a][None], H)[0]
    error = np.linalg.norm(mapped - features_b.uv[matches.index_b], axis=1)
    assert np.mean(error < 2.0) > 0.95


def test_colours_are_sampled_at_the_nearest_pixel_clamped_to_the_image():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    np.testing.assert_array_equal(sample_colors(rgb, np.array([[0.2, 0.6], [5.0, -1.0]])),
                                  [rgb[1, 0], rgb[0, 2]])


@pytest.fixture(scope="module")
def unity_sift(shared_data):
    images = list_images(shared_data / "unity_hall")
    K = find_calibration(shared_data / "unity_hall")
    config = SiftConfig(max_features=1500, workers=2)
    return images, sift_tracks(images, config, TwoViewConfig(), RansacConfig(), K=K)


def test_sift_tracks_on_unity_hall_are_multiview_and_consistent(unity_sift):
    images, result = unity_sift
    tracks = result.tracks
    assert len(result.matches_per_pair) == 10                    # 5 images: all pairs
    assert all(result.verified_per_pair[pair] <= n for pair, n in result.matches_per_pair.items())
    # A general hall scene: verified pairs are calibrated, never planar or pure rotation.
    assert {g.type for g in result.two_view.values()} == {TwoViewGeometryType.CALIBRATED}
    lengths = np.bincount(tracks.track_index)
    assert lengths.min() >= 2 and lengths.max() >= 4             # pairwise matches chained into tracks
    keys = tracks.track_index * len(images) + tracks.image_index
    assert np.unique(keys).size == keys.size                     # at most once per image
    assert np.all((tracks.uv >= 0) & (tracks.uv <= [images.width, images.height]))
    assert tracks.colors.dtype == np.uint8 and len(tracks.colors) == tracks.num_tracks
    assert result.look_alikes.pairs == [] and result.look_alikes.conflicts == []   # no symmetric object


def test_the_kept_verified_matches_join_into_the_very_tracks_sift_tracks_returned(unity_sift):
    _, result = unity_sift
    joined = joined_tracks(result.verified)
    for field in ("track_index", "image_index", "uv", "colors"):
        np.testing.assert_array_equal(getattr(joined.tracks, field), getattr(result.tracks, field))
    np.testing.assert_array_equal(joined.observation_keypoint, result.features.observation_keypoint)
    assert result.verified.per_pair() == result.verified_per_pair


def matches(index_a: list[int], index_b: list[int], ratio: list[float]) -> DescriptorMatches:
    return DescriptorMatches(np.array(index_a), np.array(index_b), np.array(ratio))


def test_a_pair_left_out_no_longer_links_its_matches_and_the_other_pairs_still_do():
    # Three images of two keypoints each: 0-1 and 1-2 match keypoint 0 to keypoint 0, 0-2 keypoint 1 to 1.
    uv = [np.array([[10.0, 10.0], [20.0, 20.0]]) + k for k in range(3)]
    colors = [np.full((2, 3), 40 * k, np.uint8) for k in range(3)]
    verified = VerifiedMatches(["a", "b", "c"], uv, colors, {
        (0, 1): matches([0], [0], [0.5]), (1, 2): matches([0], [0], [0.6]), (0, 2): matches([1], [1], [0.7])})
    everything = joined_tracks(verified)
    assert everything.tracks.num_tracks == 2 and len(everything.tracks.track_index) == 5

    without = verified.without([(0, 1)])
    assert without.per_pair() == {(0, 1): 0, (1, 2): 1, (0, 2): 1}
    joined = joined_tracks(without)
    seen_in = {track: sorted(joined.tracks.image_index[joined.tracks.track_index == track].tolist())
               for track in range(joined.tracks.num_tracks)}
    assert sorted(seen_in.values()) == [[0, 2], [1, 2]]     # image 0's keypoint 0 is in no track any more
    observations = zip(joined.tracks.image_index.tolist(), joined.tracks.uv[:, 0].tolist(), strict=True)
    keypoint_of = dict(zip(observations, joined.observation_keypoint.tolist(), strict=True))
    assert keypoint_of == {(0, 20.0): 1, (2, 22.0): 1, (1, 11.0): 0, (2, 12.0): 0}
    assert verified.per_pair() == {(0, 1): 1, (1, 2): 1, (0, 2): 1}        # the original is unchanged


def test_one_worker_detects_matches_and_verifies_exactly_as_two_do(shared_data, unity_sift):
    images, parallel = unity_sift                                  # two detecting threads, two verifiers
    serial = sift_tracks(images, SiftConfig(max_features=1500, workers=1), TwoViewConfig(), RansacConfig(),
                         K=find_calibration(shared_data / "unity_hall"))
    assert serial.matches_per_pair == parallel.matches_per_pair
    assert serial.two_view.keys() == parallel.two_view.keys()
    for pair, geometry in serial.two_view.items():                # RANSAC is seeded per pair
        assert geometry.type == parallel.two_view[pair].type
        np.testing.assert_array_equal(geometry.inlier_mask, parallel.two_view[pair].inlier_mask)
        np.testing.assert_array_equal(geometry.E, parallel.two_view[pair].E)
    np.testing.assert_array_equal(serial.tracks.track_index, parallel.tracks.track_index)
    np.testing.assert_array_equal(serial.tracks.uv, parallel.tracks.uv)
    assert set(serial.seconds_per_stage) == {"detection", "matching_and_verification", "view_graph"}


class SerialStages:
    """The chunked stages one after the other in this process, with coarse chunks (as other machines'
    workers run them), recording what they were given."""

    images_per_chunk = 2
    pairs_per_block = 3

    def __init__(self) -> None:
        self.chunks: list = []
        self.blocks: list = []

    def extract(self, chunks, config):
        self.chunks = chunks
        return (extract_chunk(chunk, config) for chunk in chunks)

    def match(self, work, blocks):
        self.blocks = blocks
        return (match_block(work, block) for block in blocks)


def test_chunks_of_images_and_blocks_of_pairs_give_what_the_pool_gives(shared_data, unity_sift):
    images, pooled = unity_sift
    stages = SerialStages()
    chunked = sift_tracks(images, SiftConfig(max_features=1500, workers=1), TwoViewConfig(), RansacConfig(),
                          K=find_calibration(shared_data / "unity_hall"), stages=stages)
    assert isinstance(stages, FeatureStages)
    assert [len(chunk) for chunk in stages.chunks] == [2, 2, 1]        # 5 images
    # Each query image's pairs stay in one block; a block closes once it holds 3 pairs.
    queries = [query for block in stages.blocks for query in block]
    assert sorted(query for query, _ in queries) == [0, 1, 2, 3]
    assert all(sum(len(partners) for _, partners in block[:-1]) < 3 for block in stages.blocks)
    assert len(stages.blocks) > 1
    assert chunked.keypoints_per_image == pooled.keypoints_per_image
    assert chunked.verified_per_pair == pooled.verified_per_pair
    np.testing.assert_array_equal(chunked.tracks.track_index, pooled.tracks.track_index)
    np.testing.assert_array_equal(chunked.tracks.uv, pooled.tracks.uv)


def test_the_worker_processes_start_before_the_images_are_detected(tmp_path, monkeypatch):
    """Their start (spawn, imports) overlaps detection; the descriptors reach them after. The calling process
    is the second of the two workers."""
    from estimation.features import sift

    texture = textured_image(200, 160, seed=5)
    for index in range(3):
        cv2.imwrite(str(tmp_path / f"{index}.png"), np.roll(texture, 6 * index, axis=1))
    detect, processes = sift._detect_in_file, []

    def counting(path, config):
        processes.append(len(multiprocessing.active_children()))
        return detect(path, config)

    monkeypatch.setattr(sift, "_detect_in_file", counting)
    result = sift_tracks(list_images(tmp_path), SiftConfig(workers=2))
    assert processes == [1, 1, 1]
    assert sum(result.matches_per_pair.values()) > 0


def test_sift_correspondences_agree_with_the_course_matches_epipolar_geometry(shared_data, unity_sift):
    images, result = unity_sift
    course = load_match_tracks(images).tracks
    for i, j in [(0, 1), (2, 3)]:
        _, course_i, course_j = course.pair_correspondences(i, j)
        F, _ = cv2.findFundamentalMat(course_i, course_j, cv2.FM_RANSAC, 1.0, 0.999)
        _, uv_i, uv_j = result.tracks.pair_correspondences(i, j)
        assert len(uv_i) >= 100
        line_j = np.c_[uv_i, np.ones(len(uv_i))] @ F.T            # epipolar lines of uv_i in image j
        residual = np.sum(line_j * np.c_[uv_j, np.ones(len(uv_j))], axis=1)
        distance = np.abs(residual) / np.hypot(line_j[:, 0], line_j[:, 1])
        # Random correspondences would lie within 3 px of the epipolar line a few percent of the time
        # (the course's own matches of these pairs are 74 % and 86 % inliers at 1 px).
        assert np.mean(distance < 3.0) > 0.9


def test_images_without_any_common_features_are_an_input_error(tmp_path):
    from PIL import Image

    for index in (1, 2):
        Image.fromarray(np.full((64, 64, 3), 40 * index, np.uint8)).save(tmp_path / f"{index}.png")
    with pytest.raises(InputError, match="SIFT found no matches between any two images"):
        sift_tracks(list_images(tmp_path), SiftConfig())


def test_a_cpu_reconstruction_never_imports_torch(tmp_path):
    """Matching runs in numpy on the CPU and "auto" asks torch for CUDA only where an NVIDIA driver is
    loaded (importing torch costs ~0.8 CPU s): a small SIFT run (one worker: all of it in this process)
    loads no torch."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (160, 200, 3), np.uint8), (3, 3), 0)
    for index in range(3):
        cv2.imwrite(str(tmp_path / f"{index}.png"), np.roll(texture, 6 * index, axis=1))
    script = textwrap.dedent(f"""
        import sys
        import estimation.features.matching as matching
        from estimation.config import SiftConfig
        from estimation.features.sift import sift_tracks
        from estimation.io.images import list_images

        matching.NVIDIA_DRIVER = {str(tmp_path / "no-driver")!r}     # as on a machine without a GPU
        result = sift_tracks(list_images({str(tmp_path)!r}), SiftConfig(device="auto", workers=1))
        print(sum(result.matches_per_pair.values()) > 0, "torch" in sys.modules)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                         cwd=REPOSITORY, env={**os.environ, "PYTHONPATH": str(REPOSITORY)})
    assert run.stdout.split() == ["True", "False"]


def test_a_gpu_matches_in_the_calling_process_and_the_workers_only_verify(monkeypatch):
    """On a device other than the CPU every query image is matched here (one device context), not in each
    worker process; the pairs and their geometry are those of the CPU path. (No GPU needed: the device's
    namespace is numpy here, and a worker that matched would fail on the empty descriptor list.)"""
    from estimation.features import sift
    from estimation.features.matching import NUMPY

    rng = np.random.default_rng(3)
    points = rng.uniform([-1, -1, 4], [1, 1, 6], (120, 3))
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    uv, descriptors = [], []
    shared = rng.integers(0, 256, (120, 128)).astype(np.uint8)
    for shift in (0.0, 0.3, 0.6):
        projected = (points + [shift, 0, 0]) @ K.T
        uv.append(projected[:, :2] / projected[:, 2:])
        descriptors.append(shared)
    pairs = [(0, 1), (0, 2), (1, 2)]
    calls = []
    monkeypatch.setattr(sift, "array_namespace", lambda device: calls.append(device) or NUMPY)
    on_cpu = sift.PairWork(uv, descriptors, 0.8, 0.7, "cpu", TwoViewConfig(), RansacConfig(), K)
    on_gpu = sift.PairWork(uv, descriptors, 0.8, 0.7, "cuda", TwoViewConfig(), RansacConfig(), K)
    cpu_matches, cpu_geometries = sift.match_and_verify_pairs(on_cpu, pairs, WorkerPool(1))
    calls.clear()
    with WorkerPool(2, modules=sift.WORKER_MODULES) as pool:
        gpu_matches, gpu_geometries = sift.match_and_verify_pairs(on_gpu, pairs, pool)
    assert calls == ["cuda", "cuda"]                               # query images 0 and 1, here
    assert all(len(m.ratio) == 120 for m in gpu_matches.values())
    for pair in pairs:
        np.testing.assert_array_equal(gpu_matches[pair].index_b, cpu_matches[pair].index_b)
        np.testing.assert_array_equal(gpu_geometries[pair].inlier_mask, cpu_geometries[pair].inlier_mask)


def test_a_large_low_contrast_image_is_measured_on_a_preview_and_masked_at_full_size():
    image = dark_low_contrast_image(seed=1)
    large = cv2.resize(image, (1600, 1200), interpolation=cv2.INTER_CUBIC)       # beyond the preview side
    fixed = detect_features(large, SiftConfig(low_contrast=0)).uv
    adaptive = detect_features(large, SiftConfig()).uv
    assert len(adaptive) > 3 * max(len(fixed), 10)
    assert adaptive[:, 0].min() > 750
