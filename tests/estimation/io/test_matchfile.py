"""The course's matching{i}.txt parser: real files, merged multi-view tracks, and broken copies."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from estimation.errors import InputError
from estimation.io.images import ImageSet
from estimation.io.matchfile import find_match_files, load_match_tracks, parse_match_file, tracks_from_rows

WIDTH, HEIGHT = 800, 600
IDS = {1, 2, 3, 4, 5}


def image_set(folder: Path) -> ImageSet:
    """Five 800x600 images named 1.png..5.png in `folder` (the parser never opens them)."""
    return ImageSet(folder=folder, paths=[folder / f"{i}.png" for i in range(1, 6)], width=WIDTH,
                    height=HEIGHT, ids={i: i - 1 for i in range(1, 6)})


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def assert_valid_tracks(tracks) -> None:
    """Every track is seen in >= 2 images, at most once per image, with pixels inside the image."""
    lengths = np.bincount(tracks.track_index, minlength=tracks.num_tracks)
    assert lengths.min() >= 2
    pairs = tracks.track_index * len(tracks.image_names) + tracks.image_index
    assert np.unique(pairs).size == pairs.size
    assert np.all((tracks.uv >= 0) & (tracks.uv <= [WIDTH, HEIGHT]))


def test_real_files_become_multiview_tracks(shared_data):
    result = load_match_tracks(image_set(shared_data / "unity_hall"))
    tracks = result.tracks
    assert_valid_tracks(tracks)
    assert tracks.image_names == ["1.png", "2.png", "3.png", "4.png", "5.png"]
    assert result.num_rows == 3833          # feature rows with n >= 2 in the four files
    assert result.num_merged_rows > 0       # rows of later files re-listing features of earlier ones
    assert tracks.num_tracks < result.num_rows
    lengths = np.bincount(tracks.track_index)
    assert lengths.max() == 5               # tracks spanning all five images are kept whole
    for i in range(5):
        for j in range(i + 1, 5):
            assert len(tracks.pair_correspondences(i, j)[0]) >= 100


def test_real_first_row_is_read_exactly(shared_data):
    path = shared_data / "unity_hall" / "matching1.txt"
    rows = parse_match_file(path, 1, IDS, WIDTH, HEIGHT)
    first = rows[0]
    assert first.line == 1                   # matching1.txt has no nFeatures header
    assert first.image_ids == (1, 3)
    np.testing.assert_array_equal(first.uv, [[5.08304, 116.978], [49.0748, 166.783]])
    np.testing.assert_array_equal(first.color, [255, 255, 255])
    assert parse_match_file(shared_data / "unity_hall" / "matching2.txt", 2, IDS, WIDTH, HEIGHT)[0].line == 2


def test_each_row_is_one_track_with_its_colour(tmp_path):
    write(tmp_path, "matching1.txt", "3 10 20 30 1 2 2 3 4 5 6 7\n2 40 50 60 8 9 3 10 11\n")
    tracks = load_match_tracks(image_set(tmp_path)).tracks
    assert tracks.num_tracks == 2
    np.testing.assert_array_equal(tracks.colors, [[10, 20, 30], [40, 50, 60]])
    np.testing.assert_array_equal(tracks.track_index, [0, 0, 0, 1, 1])
    np.testing.assert_array_equal(tracks.image_index, [0, 1, 4, 0, 2])
    np.testing.assert_array_equal(tracks.uv, [[1, 2], [3, 4], [6, 7], [8, 9], [10, 11]])


def test_rows_sharing_an_identical_observation_merge_into_one_track(tmp_path):
    # matching1 lists the feature in image 3; matching3 has a row for the same point (same pixels).
    write(tmp_path, "matching1.txt", "2 1 1 1 10 20 3 30.5 40.25\n")
    write(tmp_path, "matching3.txt", "nFeatures: 2\n2 1 1 1 30.5 40.25 5 50 60\n2 9 9 9 30.5 40.3 4 70 80\n")
    result = load_match_tracks(image_set(tmp_path))
    tracks = result.tracks
    assert result.num_merged_rows == 1
    assert tracks.num_tracks == 2           # the (3, 30.5, 40.3) row differs in v: its own track
    np.testing.assert_array_equal(tracks.image_index[tracks.track_index == 0], [0, 2, 4])
    np.testing.assert_array_equal(tracks.image_index[tracks.track_index == 1], [2, 3])


def test_a_merge_that_would_see_an_image_twice_is_refused_and_earlier_rows_win(tmp_path):
    write(tmp_path, "matching1.txt", "2 0 0 0 10 10 2 20 20\n2 0 0 0 11 11 3 30 30\n")
    # Links (2: 20,20) to (3: 30,30): that would join image-1 pixels (10,10) and (11,11).
    write(tmp_path, "matching2.txt", "2 0 0 0 20 20 3 30 30\n")
    result = load_match_tracks(image_set(tmp_path))
    assert result.num_rejected_links == 1
    assert_valid_tracks(result.tracks)
    assert result.tracks.num_tracks == 2
    np.testing.assert_array_equal(result.tracks.uv, [[10, 10], [20, 20], [11, 11], [30, 30]])


def test_files_with_and_without_the_nfeatures_header_read_the_same(tmp_path):
    body = "2 1 2 3 10 20 2 30 40\n3 4 5 6 50 60 3 70 80 4 90 100\n"
    without = parse_match_file(write(tmp_path, "matching1.txt", body), 1, IDS, WIDTH, HEIGHT)
    headed = write(tmp_path, "with_header.txt", "nFeatures: 2\n" + body)
    with_header = parse_match_file(headed, 1, IDS, WIDTH, HEIGHT)
    assert [r.image_ids for r in without] == [r.image_ids for r in with_header]
    for a, b in zip(without, with_header, strict=True):
        np.testing.assert_array_equal(a.uv, b.uv)
    assert [r.line for r in with_header] == [2, 3]


def test_rows_seen_in_one_image_only_make_no_track(tmp_path):
    rows = parse_match_file(write(tmp_path, "matching1.txt", "1 1 2 3 10 20\n"), 1, IDS, WIDTH, HEIGHT)
    assert rows == []
    assert tracks_from_rows(rows, {i: i - 1 for i in IDS}, [f"{i}.png" for i in IDS]).tracks.num_tracks == 0


def test_match_files_are_found_by_name_and_keyed_by_image_id(shared_data):
    files = find_match_files(shared_data / "unity_hall")
    assert sorted(files) == [1, 2, 3, 4]
    assert files[3].name == "matching3.txt"


# Each malformation of one row of a copy of the real matching1.txt names the file, the line and why.
def replace(index: int, value: str):
    """A malformation: token `index` of the row becomes `value`."""
    return lambda tokens: tokens[:index] + [value] + tokens[index + 1:]


# Row 2 of matching1.txt is "3 79 71 51 7.15528 197.921 2 11.255 225.237 5 259.685 103.719".
BROKEN_ROWS = {
    "truncated row": (lambda tokens: tokens[:-2], r"truncated row: n = 3 needs 12 values, found 10"),
    "truncated before the first pixel": (lambda tokens: tokens[:4], r"truncated row"),
    "n inconsistent with the triples": (lambda tokens: tokens + ["4", "1", "2"], r"n = 3 is inconsistent"),
    "non-numeric value": (replace(4, "abc"), r"non-numeric value 'abc'"),
    "non-numeric n": (replace(0, "three"), r"non-numeric value 'three'"),
    "fractional image id": (replace(6, "2.5"), r"image id must be an integer"),
    "unknown image id": (replace(6, "9"), r"unknown image id 9"),
    "image id equal to own id": (replace(6, "1"), r"image id 1 is the file's own image"),
    "image id repeated": (replace(9, "2"), r"image id 2 appears twice"),
    "u outside the image": (replace(4, "800.5"), r"coordinates \(800\.5, 197\.921\) in image 1 lie outside"),
    "negative v in another image": (replace(8, "-3"), r"coordinates \(11\.255, -3\) in image 2 lie outside"),
    "colour out of range": (replace(1, "300"), r"colour 300 71 51 outside 0\.\.255"),
    "infinite coordinate": (replace(4, "inf"), r"non-finite value 'inf'"),
}


@pytest.mark.parametrize("malformation", sorted(BROKEN_ROWS))
def test_a_broken_row_is_an_input_error_naming_file_and_line(shared_data, tmp_path, malformation):
    lines = (shared_data / "unity_hall" / "matching1.txt").read_text().splitlines()
    target = 1                                   # 0-based: line 2, "3 79 71 51 7.15528 197.921 2 ... 5 ..."
    assert lines[target].split()[0] == "3"
    break_row, reason = BROKEN_ROWS[malformation]
    lines[target] = " ".join(break_row(lines[target].split()))
    path = write(tmp_path, "matching1.txt", "\n".join(lines) + "\n")
    with pytest.raises(InputError, match=re.escape(f"{path}, line 2: ") + reason):
        load_match_tracks(image_set(tmp_path))


def test_a_header_after_the_first_line_is_an_input_error(tmp_path):
    path = write(tmp_path, "matching2.txt", "2 1 1 1 10 10 3 20 20\nnFeatures: 4\n")
    with pytest.raises(InputError, match=re.escape(f"{path}, line 2: the 'nFeatures:' header")):
        load_match_tracks(image_set(tmp_path))


def test_a_non_numeric_header_count_is_an_input_error(tmp_path):
    path = write(tmp_path, "matching2.txt", "nFeatures: many\n2 1 1 1 10 10 3 20 20\n")
    with pytest.raises(InputError, match=re.escape(f"{path}, line 1: ") + "non-numeric value 'many'"):
        load_match_tracks(image_set(tmp_path))


def test_a_match_file_of_an_image_that_does_not_exist_is_an_input_error(tmp_path):
    path = write(tmp_path, "matching7.txt", "2 1 1 1 10 10 3 20 20\n")
    with pytest.raises(InputError, match=re.escape(str(path)) + ".*no image with id 7"):
        load_match_tracks(image_set(tmp_path))


def test_a_folder_without_match_files_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="no matching"):
        load_match_tracks(image_set(tmp_path))
