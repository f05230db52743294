"""`sfmnerf reconstruct VIDEO` and `sfmnerf scene VIDEO`: a video file where a photos folder goes."""

from __future__ import annotations

import json

from click.testing import CliRunner

from service.cli import main
from tests.estimation.io.clips import encode_clip, held_views, lego_centres, walk_order


def test_reconstruct_takes_a_video_and_reports_its_keyframes(tmp_path):
    frames, _ = held_views(walk_order(lego_centres(), 40), hold=1)
    clip = encode_clip(frames, tmp_path / "walk.mp4", fps=10)
    result = CliRunner().invoke(main, ["reconstruct", str(clip), "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    keyframes = report["video"]["keyframes"]
    blurred = report["video"]["blurred_frames"]
    assert f"video walk.mp4: 40 frames, {blurred} blurred, {keyframes} keyframes in frames/" in result.output
    assert "no focal length in the container" in result.output
    assert len(list((tmp_path / "out" / "frames").glob("*.jpg"))) == keyframes == report["images_total"]
    assert f"registered {report['images_registered']}/{keyframes} images" in result.output


def test_a_corrupt_video_is_a_one_line_error_naming_it(tmp_path):
    clip = tmp_path / "broken.mov"
    clip.write_bytes(b"\x00\x00\x00\x14ftypqt  " + bytes(3000))
    for command in (["reconstruct", str(clip), "--out", str(tmp_path / "a")],
                    ["scene", str(clip), "--out", str(tmp_path / "b"), "--steps", "1"]):
        result = CliRunner().invoke(main, command)
        assert result.exit_code == 1, result.output
        lines = result.output.strip().splitlines()
        assert lines[-1].startswith("Error: ") and "broken.mov" in lines[-1], result.output
        assert "Traceback" not in result.output
