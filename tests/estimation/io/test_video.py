"""A video as input: decoding, blur rejection, keyframe selection and its bounds, bad files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from estimation.config import CameraConfig, VideoConfig
from estimation.errors import InputError
from estimation.io.images import exif_focal, list_images
from estimation.io.video import (
    blurred_frames,
    extract_keyframes,
    frame_motion,
    greedy_keyframes,
    is_video,
    keyframe_bounds,
    probe_video,
    select_keyframes,
    sharpness,
)
from estimation.pipeline import initial_intrinsics
from tests.estimation.io.clips import encode_clip, held_views, lego_centres, walk_order

FOCAL_KEY = "com.apple.quicktime.camera.focal_length.35mm_equivalent"


@pytest.fixture(scope="module")
def lego_clip(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    """12 lego views along a walk, each held 3 frames at 10 fps, the first frame of views 4 and 8 blurred;
    the container says the focal length is 26 mm (35 mm equivalent)."""
    names = walk_order(lego_centres(), 12)
    frames, sources = held_views(names, hold=3, blur_first_of=(4, 8))
    folder = tmp_path_factory.mktemp("clip")
    return encode_clip(frames, folder / "walk.mp4", fps=10, metadata={FOCAL_KEY: "26"}), sources


def test_probe_reads_size_rate_duration_and_the_container_focal_length(lego_clip):
    path, sources = lego_clip
    info = probe_video(path)
    assert (info.width, info.height, info.codec, info.rotation_deg) == (200, 200, "h264", 0)
    assert info.fps == pytest.approx(10.0)
    assert info.duration_s == pytest.approx(len(sources) / 10.0, abs=0.15)
    assert info.focal_35mm == 26.0
    assert is_video(path) and not is_video(path.parent)


def test_keyframes_are_sharp_frames_written_as_images_with_the_focal_length(lego_clip, tmp_path):
    path, sources = lego_clip
    keyframes = extract_keyframes(path, tmp_path / "frames")
    assert keyframes.frames_decoded == len(sources)
    indices = keyframes.selection.indices
    blurred_indices = {4 * 3, 8 * 3}
    assert not blurred_indices & set(indices)          # the blurred first frames are never keyframes
    assert keyframes.blurred_frames >= 2
    # A keyframe at most one view late: the view after a jump is taken from its first sharp frame.
    assert [sources[i] for i in indices] == list(dict.fromkeys(sources[i] for i in indices))
    images = list_images(tmp_path / "frames")
    assert [p.name for p in images.paths] == [f"{i:06d}.jpg" for i in indices]
    assert (images.width, images.height) == (200, 200)
    focal_px = 26.0 / np.hypot(36, 24) * np.hypot(200, 200)
    assert exif_focal(images.paths[0], (2.0, 150.0)).focal_px == pytest.approx(focal_px, rel=1e-6)
    initial = initial_intrinsics(images, None, CameraConfig())       # what the reconstruction starts from
    assert initial.source == "exif" and initial.cameras[0].fx == pytest.approx(focal_px, rel=1e-6)
    assert keyframes.summary()["focal_source"] == "container metadata"


def test_sharpness_falls_with_blur_and_a_blurred_frame_among_sharp_ones_is_flagged():
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 255, (50, 50), dtype=np.uint8), (200, 200))
    blurred = cv2.GaussianBlur(texture, (0, 0), 2.0)
    assert sharpness(blurred) < 0.5 * sharpness(texture)
    values = np.array([sharpness(texture)] * 10 + [sharpness(blurred)] + [sharpness(texture)] * 10)
    assert np.flatnonzero(blurred_frames(values, window=5, ratio=0.6)).tolist() == [10]
    assert np.flatnonzero(blurred_frames(values[10:], window=5, ratio=0.6)).tolist() == [0]   # at the start
    # A scene that gets less textured slowly is not blur.
    assert not blurred_frames(np.linspace(100.0, 50.0, 60), window=5, ratio=0.6).any()


def test_frame_motion_measures_a_shift_as_a_fraction_of_the_diagonal():
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 1.5)
    shifted = np.roll(texture, 8, axis=1)
    motion = frame_motion(texture[:, 20:-20], shifted[:, 20:-20], max_corners=200)
    assert motion.flow == pytest.approx(8 / np.hypot(240, 280), rel=0.05)
    assert motion.survival > 0.8
    still = frame_motion(texture, texture, max_corners=200)
    assert still.flow == pytest.approx(0.0, abs=1e-3) and still.survival > 0.95


def test_greedy_keyframes_wait_for_enough_novelty_and_skip_unusable_frames():
    novelty = np.array([0, 0.5, 0.6, 0.2, 1.0, 0.1, 0.1])
    usable = np.array([True, True, True, True, False, True, True])
    # 0.5 + 0.6 reaches 1 at frame 2; 0.2 + 1.0 at frame 4, unusable, so frame 5.
    assert greedy_keyframes(novelty, usable, 1.0) == [0, 2, 5]



def test_a_keyframe_reached_by_a_jump_keeps_the_frame_before_the_jump_as_a_bridge():
    # Frame 3 lies 0.6 of a spacing from keyframe 0; the jump 3 -> 4 alone is 2.5 spacings: frame 3 shares
    # more with each side than keyframes 0 and 4 share with each other.
    novelty = np.array([0, 0.3, 0.2, 0.1, 2.5, 0.1, 0.1])
    usable = np.ones(len(novelty), bool)
    assert greedy_keyframes(novelty, usable, 1.0) == [0, 4]
    assert greedy_keyframes(novelty, usable, 1.0, bridge_share=0.5) == [0, 3, 4]
    # Too near the last keyframe (0.2 of a spacing), the frame before the jump is a near-duplicate of it.
    assert greedy_keyframes(np.array([0, 0.1, 0.1, 2.5]), np.ones(4, bool), 1.0, bridge_share=0.5) == [0, 3]
    # A keyframe reached gradually (no single step of a spacing) needs no bridge.
    assert greedy_keyframes(np.array([0, 0.4, 0.4, 0.4]), np.ones(4, bool), 1.0, bridge_share=0.5) == [0, 3]
    # An unusable frame before the jump is never a bridge: the last usable one is.
    usable = np.array([True, True, True, False, True])
    assert greedy_keyframes(np.array([0, 0.3, 0.4, 0.1, 2.5]), usable, 1.0, bridge_share=0.5) == [0, 2, 4]


@pytest.mark.parametrize(("per_frame_novelty", "expected"), [
    (0.5, "most"),        # fast camera: 900 keyframes at spacing 1, thinned to the maximum
    (0.06, "natural"),    # 108 keyframes at spacing 1: within the bounds, kept
    (0.02, "fewest"),     # slow camera: 36 at spacing 1, the spacing shrinks to reach the minimum
])
def test_a_minute_of_video_gives_100_to_300_keyframes(per_frame_novelty, expected):
    frames = 60 * 30
    novelty = np.full(frames, per_frame_novelty)
    blurred = np.zeros(frames, bool)
    blurred[::7] = True
    config = VideoConfig()
    assert keyframe_bounds(60.0, config) == (100, 300)
    selection = select_keyframes(novelty, blurred, 60.0, config)
    count = len(selection.indices)
    assert 100 <= count <= 300
    assert not blurred[selection.indices].any()
    if expected == "most":
        assert count > 200 and selection.spacing > 1   # thinned only as far as needed
    elif expected == "fewest":
        assert count <= 110 and selection.spacing < 1
    else:
        assert selection.spacing == 1.0


def test_a_still_camera_gives_few_keyframes_not_near_duplicates():
    selection = select_keyframes(np.full(1800, 1e-3), np.zeros(1800, bool), 60.0, VideoConfig())
    assert selection.spacing == VideoConfig().min_spacing_factor
    assert len(selection.indices) < 10


def test_a_corrupt_video_is_an_error_naming_the_file(lego_clip, tmp_path):
    path, _ = lego_clip
    truncated = tmp_path / "truncated.mp4"
    truncated.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 3])
    garbage = tmp_path / "garbage.mov"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    for bad in (truncated, garbage):
        with pytest.raises(InputError, match=bad.name):
            extract_keyframes(bad, tmp_path / "frames")


def test_an_image_named_like_a_video_is_refused_as_unsupported(tmp_path):
    fake = tmp_path / "photo.mp4"
    cv2.imwrite(str(tmp_path / "photo.png"), np.zeros((32, 32, 3), np.uint8))
    (tmp_path / "photo.png").rename(fake)
    with pytest.raises(InputError, match=r"photo\.mp4: .*not a supported video"):
        probe_video(fake)


def test_decoding_stops_with_an_error_beyond_the_frame_limit(lego_clip, tmp_path):
    path, _ = lego_clip
    with pytest.raises(InputError, match=r"walk\.mp4: more than 20 frames"):
        extract_keyframes(path, tmp_path / "frames", VideoConfig(max_frames=20))
