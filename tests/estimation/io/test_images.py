"""Listing the images folder and loading K: what is an image, its id and order, and bad calibrations."""

from __future__ import annotations

import io
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import ExifTags, Image

from estimation.errors import InputError
from estimation.io.images import exif_focal, find_calibration, list_images, load_calibration, load_rgb

UNITY_K = np.array([
    [531.122155322710, 0.0, 407.192550839899],
    [0.0, 531.541737503901, 313.308715048366],
    [0.0, 0.0, 1.0],
])


def save_image(path: Path, width: int = 40, height: int = 30) -> Path:
    Image.fromarray(np.full((height, width, 3), 128, np.uint8)).save(path)
    return path


def test_unity_hall_has_five_images_in_numeric_order_with_their_ids(shared_data):
    images = list_images(shared_data / "unity_hall")
    assert images.names == ["1.png", "2.png", "3.png", "4.png", "5.png"]
    assert images.ids == {1: 0, 2: 1, 3: 2, 4: 3, 5: 4}
    assert (images.width, images.height) == (800, 600)
    assert load_rgb(images.paths[0]).shape == (600, 800, 3)


def test_png_and_jpeg_of_any_name_are_images_and_other_files_are_ignored(tmp_path):
    for name in ["10.png", "2.PNG", "b.JPEG", "a.jpg"]:
        save_image(tmp_path / name)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "matching2.txt").write_text("")
    (tmp_path / "sub.png").mkdir()
    images = list_images(tmp_path)
    assert images.names == ["2.PNG", "10.png", "a.jpg", "b.JPEG"]     # numeric stems by value first
    assert images.ids == {2: 0, 10: 1}
    assert (images.width, images.height) == (40, 30)


def test_the_names_are_listed_once_not_per_lookup(tmp_path):
    for name in ["1.png", "2.png"]:
        save_image(tmp_path / name)
    images = list_images(tmp_path)
    assert images.names is images.names        # reports look a name up per image pair


def test_images_of_different_sizes_are_an_input_error_naming_the_odd_one(tmp_path):
    save_image(tmp_path / "1.png")
    save_image(tmp_path / "2.png")
    odd = save_image(tmp_path / "3.png", width=41)
    with pytest.raises(InputError, match=re.escape(f"{odd}: image is 41x30 but 1.png is 40x30")):
        list_images(tmp_path)


def test_fewer_than_two_images_is_an_input_error(tmp_path):
    save_image(tmp_path / "1.png")
    with pytest.raises(InputError, match="found 1 PNG/JPEG image.*at least 2"):
        list_images(tmp_path)


def test_a_missing_folder_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        list_images(tmp_path / "nowhere")


def test_an_unreadable_image_is_an_input_error_naming_it(tmp_path):
    save_image(tmp_path / "1.png")
    broken = tmp_path / "2.png"
    broken.write_bytes(b"not a png at all")
    with pytest.raises(InputError, match=re.escape(f"{broken}: not a readable")):
        list_images(tmp_path)


def test_unity_hall_calibration_is_read_exactly(shared_data):
    np.testing.assert_array_equal(find_calibration(shared_data / "unity_hall"), UNITY_K)


def test_a_given_calibration_file_overrides_the_folder_one(shared_data, tmp_path):
    other = tmp_path / "K.txt"
    other.write_text("500 0 400\n0 500 300\n0 0 1\n")
    K = find_calibration(shared_data / "unity_hall", other)
    np.testing.assert_array_equal(K, [[500, 0, 400], [0, 500, 300], [0, 0, 1]])


BAD_CALIBRATIONS = {
    "two rows": ("500 0 400\n0 500 300\n", r"{path}: expected a 3x3 matrix .* found 2 rows"),
    "short row": ("500 0 400\n0 500\n0 0 1\n", r"{path}, line 2: expected 3 numbers .* found 2"),
    "non-numeric": ("500 0 400\n0 f 300\n0 0 1\n", r"{path}, line 2: non-numeric value 'f'"),
    "singular": ("500 0 400\n1000 0 800\n0 0 1\n", r"{path}: K is singular"),
    "zero focal": ("0 0 400\n0 500 300\n0 0 1\n", r"{path}: K is singular"),
    "not a camera matrix": ("500 0 400\n0 500 300\n0 1 1\n", r"{path}: the last row of K must be 0 0 1"),
    "negative focal": ("-500 0 400\n0 500 300\n0 0 1\n", r"{path}: focal lengths .* must be positive"),
    "nan": ("500 0 400\n0 nan 300\n0 0 1\n", r"{path}, line 2: non-finite value 'nan'"),
}


@pytest.mark.parametrize("case", sorted(BAD_CALIBRATIONS))
def test_a_bad_calibration_is_an_input_error_naming_the_file(tmp_path, case):
    text, expected = BAD_CALIBRATIONS[case]
    path = tmp_path / "calibration.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=expected.format(path=re.escape(str(path)))):
        load_calibration(path)


def test_a_folder_without_calibration_has_none_but_a_named_missing_file_is_an_input_error(tmp_path):
    assert find_calibration(tmp_path) is None
    expected = f"{tmp_path / 'other.txt'}: calibration file not found"
    with pytest.raises(InputError, match=re.escape(expected)):
        find_calibration(tmp_path, tmp_path / "other.txt")


# --- EXIF -----------------------------------------------------------------------------------------

PLAUSIBLE_FOV = (2.0, 150.0)


def save_jpeg_with_exif(path: Path, exif_tags: dict, orientation: int | None = None, width: int = 60,
                        height: int = 40) -> Path:
    """A JPEG whose EXIF sub-IFD holds `exif_tags` (and IFD0 the orientation, when given)."""
    pixels = np.zeros((height, width, 3), np.uint8)
    pixels[: height // 2, : width // 2] = 255           # a white top-left quadrant shows the rotation
    exif = Image.Exif()
    if orientation is not None:
        exif[ExifTags.Base.Orientation] = orientation
    exif.get_ifd(ExifTags.IFD.Exif).update(exif_tags)
    Image.fromarray(pixels).save(path, exif=exif)
    return path


def test_exif_35mm_equivalent_focal_length_is_converted_on_the_frame_diagonal(tmp_path):
    path = save_jpeg_with_exif(tmp_path / "a.jpg", {ExifTags.Base.FocalLengthIn35mmFilm: 28})
    focal = exif_focal(path, PLAUSIBLE_FOV)
    assert focal.source == "FocalLengthIn35mmFilm" and focal.problem is None
    assert focal.focal_px == pytest.approx(28 / np.hypot(36, 24) * np.hypot(60, 40))


def test_exif_focal_length_in_mm_uses_the_focal_plane_resolution(tmp_path):
    # 4.2 mm lens, 1000 pixels per cm on the sensor (unit 3 = cm), file not resized: 420 px.
    tags = {ExifTags.Base.FocalLength: 4.2, ExifTags.Base.FocalPlaneXResolution: 1000.0,
            ExifTags.Base.FocalPlaneResolutionUnit: 3}
    focal = exif_focal(save_jpeg_with_exif(tmp_path / "a.jpg", tags, width=600, height=400), PLAUSIBLE_FOV)
    assert focal.source == "FocalLength+FocalPlaneXResolution"
    assert focal.focal_px == pytest.approx(420.0)
    # the same photo downsized to 300 px wide (ExifImageWidth keeps the original 600): 210 px
    tags[ExifTags.Base.ExifImageWidth] = 600
    focal = exif_focal(save_jpeg_with_exif(tmp_path / "b.jpg", tags, width=300, height=200), PLAUSIBLE_FOV)
    assert focal.focal_px == pytest.approx(210.0)


@pytest.mark.parametrize(("tags", "problem"), [
    ({ExifTags.Base.FocalLengthIn35mmFilm: 0}, "is not a positive focal length"),
    ({ExifTags.Base.FocalLengthIn35mmFilm: 1}, "absurd field of view of 174 deg"),
    ({ExifTags.Base.FocalLengthIn35mmFilm: 5000}, "absurd field of view of 0.4"),
    ({}, "no EXIF focal length"),
])
def test_exif_that_lies_or_is_missing_gives_no_focal_and_says_why(tmp_path, tags, problem):
    focal = exif_focal(save_jpeg_with_exif(tmp_path / "a.jpg", tags), PLAUSIBLE_FOV)
    assert focal.focal_px is None
    assert re.search(problem, focal.problem)


def test_exif_orientation_is_applied_to_the_size_and_the_pixels(tmp_path):
    save_jpeg_with_exif(tmp_path / "1.jpg", {}, orientation=6)       # 6: stored image turned 90 deg clockwise
    save_jpeg_with_exif(tmp_path / "2.jpg", {}, orientation=6)
    images = list_images(tmp_path)
    assert (images.width, images.height) == (40, 60)
    rgb = load_rgb(images.paths[0])
    assert rgb.shape == (60, 40, 3)
    assert rgb[5, -5].mean() > 200 and rgb[5, 5].mean() < 50       # the white quadrant is now top-right


def png_bytes_with_exif_after_pixels(orientation: int) -> bytes:
    """A 60x40 PNG whose orientation is in an eXIf chunk after its pixel data (PIL writes eXIf before it)."""
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(buffer, format="PNG")
    exif = Image.Exif()
    exif[ExifTags.Base.Orientation] = orientation
    data = exif.tobytes()
    chunk = struct.pack(">I", len(data)) + b"eXIf" + data + struct.pack(">I", zlib.crc32(b"eXIf" + data))
    whole = buffer.getvalue()
    end = whole.rindex(b"IEND") - 4                     # IEND's length field starts its chunk
    return whole[:end] + chunk + whole[end:]


@pytest.mark.parametrize("after_pixels", [False, True])
def test_a_png_orientation_is_applied_wherever_its_exif_chunk_lies(tmp_path, after_pixels):
    for name in ("1.png", "2.png"):
        if after_pixels:
            (tmp_path / name).write_bytes(png_bytes_with_exif_after_pixels(orientation=6))
        else:
            exif = Image.Exif()
            exif[ExifTags.Base.Orientation] = 6
            Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(tmp_path / name, exif=exif)
    images = list_images(tmp_path)
    assert (images.width, images.height) == (40, 60)
    assert load_rgb(images.paths[0]).shape == (60, 40, 3)


def test_listing_pngs_reads_their_headers_not_their_pixels(tmp_path):
    # The pixel data cut short: listing still works (the pixels are read, and the cut found, at loading).
    whole = (save_image(tmp_path / "1.png", width=64, height=48)).read_bytes()
    save_image(tmp_path / "2.png", width=64, height=48)
    idat = whole.index(b"IDAT")
    (tmp_path / "1.png").write_bytes(whole[: idat + 12])
    images = list_images(tmp_path)
    assert (images.width, images.height) == (64, 48)
    with pytest.raises(InputError, match="1.png: not a readable"):
        load_rgb(images.paths[0])
