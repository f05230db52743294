"""Parser of the course's `matching{i}.txt` files into multi-view `Tracks`.

Format (one file per image i, optional first line `nFeatures: N`), one feature of image i per row:
`n r g b u_i v_i [j u_j v_j]...` where n counts the images the feature is seen in (i included),
`r g b` is its colour and each triple gives another image id j and the pixel coordinates there.

Every row is one multi-view track. The same physical feature can appear as a row in several files
(image 1's row lists image 3, and image 3's file has a row for the same point); rows that share an
identical (image, u, v) observation are merged into one track (union-find), unless the merge would
give the track two different observations in one image (a wrong match in one of the rows): that
link is refused, earlier rows winning.
"""

from __future__ import annotations

import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimation.errors import InputError
from estimation.features.track_building import assemble_tracks
from estimation.io.images import ImageSet
from estimation.types import Tracks

MATCH_FILE_PATTERN = re.compile(r"^matching(\d+)\.txt$")
HEADER_PATTERN = re.compile(r"^nFeatures\s*:\s*(\S+)\s*$")
VALUES_BEFORE_MATCHES = 6          # n r g b u_i v_i
VALUES_PER_MATCH = 3               # j u_j v_j


@dataclass(frozen=True)
class MatchRow:
    """One feature row: the images it is seen in (own image first), its pixels there and its colour."""

    file: Path
    line: int
    image_ids: tuple[int, ...]
    uv: np.ndarray          # (n, 2)
    color: np.ndarray       # (3,) uint8


@dataclass(frozen=True)
class MatchParseResult:
    """Tracks from all match files, and how they were formed."""

    tracks: Tracks
    num_rows: int                       # feature rows read (rows with n >= 2)
    num_merged_rows: int                # rows that joined a track started by another row
    num_rejected_links: int             # row links refused: they would put an image twice in a track


class _RowError(Exception):
    """A reason a row is malformed; the caller adds the file and line."""


def find_match_files(folder: Path) -> dict[int, Path]:
    """The `matching{i}.txt` files of a folder, keyed by the image id i."""
    found = {}
    for path in sorted(Path(folder).iterdir()):
        match = MATCH_FILE_PATTERN.match(path.name)
        if match and path.is_file():
            found[int(match.group(1))] = path
    return found


def _number(token: str, what: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise _RowError(f"non-numeric value {token!r} for {what}") from None
    if not np.isfinite(value):
        raise _RowError(f"non-finite value {token!r} for {what}")
    return value


def _integer(token: str, what: str) -> int:
    value = _number(token, what)
    if value != int(value):
        raise _RowError(f"{what} must be an integer, got {token!r}")
    return int(value)


def _pixel(u_token: str, v_token: str, image_id: int, width: int, height: int) -> tuple[float, float]:
    u = _number(u_token, f"u in image {image_id}")
    v = _number(v_token, f"v in image {image_id}")
    if not (0.0 <= u <= width and 0.0 <= v <= height):
        raise _RowError(
            f"coordinates ({u_token}, {v_token}) in image {image_id} lie outside the {width}x{height} image"
        )
    return u, v


def parse_match_row(
    tokens: list[str], own_id: int, valid_ids: Collection[int], width: int, height: int
) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """(image ids, uv (n, 2), colour (3,)) of one row's tokens; _RowError with the reason otherwise."""
    if len(tokens) < VALUES_BEFORE_MATCHES:
        raise _RowError(
            f"truncated row: {len(tokens)} values, a row needs at least {VALUES_BEFORE_MATCHES} (n r g b u v)"
        )
    n = _integer(tokens[0], "n (number of images)")
    if n < 1:
        raise _RowError(f"n (number of images) must be at least 1, got {tokens[0]}")
    expected = VALUES_BEFORE_MATCHES + VALUES_PER_MATCH * (n - 1)
    if len(tokens) < expected:
        raise _RowError(f"truncated row: n = {n} needs {expected} values, found {len(tokens)}")
    if len(tokens) > expected:
        raise _RowError(f"n = {n} is inconsistent with the row's {len(tokens)} values (expected {expected})")
    color = np.array([_integer(t, name) for t, name in zip(tokens[1:4], "rgb", strict=True)])
    if np.any((color < 0) | (color > 255)):
        raise _RowError(f"colour {' '.join(tokens[1:4])} outside 0..255")
    image_ids = [own_id]
    uv = [_pixel(tokens[4], tokens[5], own_id, width, height)]
    for k in range(n - 1):
        start = VALUES_BEFORE_MATCHES + VALUES_PER_MATCH * k
        image_id = _integer(tokens[start], "image id")
        if image_id == own_id:
            raise _RowError(f"image id {image_id} is the file's own image")
        if image_id not in valid_ids:
            raise _RowError(f"unknown image id {image_id} (images: {sorted(valid_ids)})")
        if image_id in image_ids:
            raise _RowError(f"image id {image_id} appears twice in the row")
        image_ids.append(image_id)
        uv.append(_pixel(tokens[start + 1], tokens[start + 2], image_id, width, height))
    return tuple(image_ids), np.array(uv, float), color.astype(np.uint8)


def parse_match_file(
    path: Path, own_id: int, valid_ids: Collection[int], width: int, height: int
) -> list[MatchRow]:
    """All feature rows of one `matching{own_id}.txt`; InputError naming the file and line otherwise."""
    path = Path(path)
    if own_id not in valid_ids:
        raise InputError(
            f"{path}: there is no image with id {own_id} in the folder (image ids: {sorted(valid_ids)})"
        )
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read the match file ({error})") from None
    rows = []
    seen_content = False
    for line_number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        header = HEADER_PATTERN.match(line.strip())
        if header:
            if seen_content:
                raise InputError(
                    f"{path}, line {line_number}: the 'nFeatures:' header is only allowed on the first line"
                )
            try:
                _integer(header.group(1), "nFeatures")
            except _RowError as error:
                raise InputError(f"{path}, line {line_number}: {error}") from None
            seen_content = True
            continue
        seen_content = True
        try:
            image_ids, uv, color = parse_match_row(line.split(), own_id, valid_ids, width, height)
        except _RowError as error:
            raise InputError(f"{path}, line {line_number}: {error}") from None
        if len(image_ids) >= 2:
            rows.append(MatchRow(file=path, line=line_number, image_ids=image_ids, uv=uv, color=color))
    return rows


def tracks_from_rows(
    rows: list[MatchRow], image_index_of_id: Mapping[int, int], image_names: list[str]
) -> MatchParseResult:
    """One track per row, rows sharing an identical (image, u, v) observation merged."""
    node_of_observation: dict[tuple[int, float, float], int] = {}
    node_image, node_uv, node_color, links = [], [], [], []
    merged_rows = 0
    for row in rows:
        nodes_before_row = len(node_image)
        row_nodes = []
        for image_id, (u, v) in zip(row.image_ids, row.uv, strict=True):
            key = (image_id, float(u), float(v))
            node = node_of_observation.get(key)
            if node is None:
                node = node_of_observation[key] = len(node_image)
                node_image.append(image_index_of_id[image_id])
                node_uv.append((u, v))
                node_color.append(row.color)
            row_nodes.append(node)
        merged_rows += min(row_nodes) < nodes_before_row
        links.extend((row_nodes[0], other) for other in row_nodes[1:])
    assembly = assemble_tracks(
        image_names,
        np.array(node_image, np.int64),
        np.array(node_uv, float).reshape(-1, 2),
        np.array(node_color, np.uint8).reshape(-1, 3),
        np.array(links, np.int64).reshape(-1, 2),
    )
    return MatchParseResult(
        tracks=assembly.tracks,
        num_rows=len(rows),
        num_merged_rows=merged_rows,
        num_rejected_links=assembly.num_rejected_links,
    )


def load_match_tracks(images: ImageSet, match_files: Mapping[int, Path] | None = None) -> MatchParseResult:
    """Tracks from the `matching{i}.txt` files of the images folder (or the given {id: path})."""
    files = find_match_files(images.folder) if match_files is None else dict(match_files)
    if not files:
        raise InputError(f"{images.folder}: no matching{{i}}.txt files found")
    if not images.ids:
        raise InputError(
            f"{images.folder}: match files name images by numeric file stem, but no image is named like 1.png"
        )
    valid_ids = set(images.ids)
    rows = []
    for own_id, path in sorted(files.items()):
        rows.extend(parse_match_file(path, own_id, valid_ids, images.width, images.height))
    return tracks_from_rows(rows, images.ids, images.names)
