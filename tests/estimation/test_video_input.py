"""`reconstruct` of a video file: its keyframes, written as images, reconstruct as photos would."""

from __future__ import annotations

import json

import numpy as np
import pytest

from estimation import InputError, ReconstructionConfig, reconstruct
from estimation.geometry.alignment import aligned_pose_errors
from tests.estimation.io.clips import encode_clip, held_views, lego_true_poses, walk_order

LEGO_FOCAL_PX = 0.5 * 200 / np.tan(0.5 * 0.6911112070083618)


def test_a_short_lego_clip_reconstructs_with_every_keyframe_registered(tmp_path):
    """75 lego views along a walk, 2 frames each at 10 fps (3 first frames blurred), H.264; with lego's K
    (the focal length from the container's metadata is tested in tests/estimation/io)."""
    truth = lego_true_poses()
    names = walk_order({name: pose.center for name, pose in truth.items()}, len(truth))
    frames, sources = held_views(names, hold=2, blur_first_of=(10, 30, 50))
    clip = encode_clip(frames, tmp_path / "lego.mp4", fps=10)
    np.savetxt(tmp_path / "calibration.txt", [[LEGO_FOCAL_PX, 0, 99.5], [0, LEGO_FOCAL_PX, 99.5], [0, 0, 1]])

    result = reconstruct(clip, tmp_path / "out",
                         ReconstructionConfig(write_figures=False, calibration=tmp_path / "calibration.txt"))

    report = result.report
    video = report["video"]
    assert video["frames_decoded"] == len(frames) and video["blurred_frames"] >= 3
    assert video["keyframes"] == report["images_total"] >= 25          # 15 s of video: >= 100 per minute
    # At most one keyframe may stay out: the walk jumps 19-24 deg on both sides of one front view (r_76),
    # which then shares 18-24 tracks with the model and gives PnP 10-11 inliers, under the registration floor
    # of 12 (its photos of the same views stay out too); guided 2D-3D matching finds none of its 206
    # keypoints distinctive among the ~1,400 points its failed pose has in view.
    assert report["images_registered"] >= report["images_total"] - 1, report["unregistered"]
    names_by_index = result.model.image_names
    registered = sorted(result.model.poses)
    true = [truth[sources[int(names_by_index[i].split(".")[0])]] for i in registered]
    errors = aligned_pose_errors([result.model.poses[i] for i in registered], true)
    assert errors.rotation_deg.mean() < 0.8 and errors.rotation_deg.max() < 4.0
    # Every later stage reads the keyframes as ordinary images under OUT/frames.
    transforms = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert all(frame["file_path"].startswith("frames/") for frame in transforms["frames"])
    assert all((tmp_path / "out" / frame["file_path"]).is_file() for frame in transforms["frames"])


def test_a_corrupt_video_is_an_input_error_naming_it(tmp_path):
    clip = tmp_path / "broken.mp4"
    clip.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(4000))
    with pytest.raises(InputError, match=r"broken\.mp4"):
        reconstruct(clip, tmp_path / "out")
