"""Descriptor matching: nearest neighbours by batched distance matrices, Lowe's ratio test and a mutual
(cross) check.

One image is matched against all its partner images at once: the partners' descriptors are stacked
into zero-padded (J, F, 128) blocks of partners of similar size (padding far from everything), and the
squared distances ||a||^2 + ||b||^2 - 2 a.b come from one matrix product per block of query rows. The
block work is written once against an array namespace (`ArrayNamespace`): numpy (its BLAS) on the CPU, so
that a CPU reconstruction never imports torch (0.8 CPU s), and torch on a CUDA device.
"""

from __future__ import annotations

import os
import sys
from types import ModuleType
from typing import Any, Literal, NamedTuple

import numpy as np

DISTANCE_BLOCK_ELEMENTS = 1 << 24
"""Entries of the distance matrix held at once (64 MiB of float32): bounds memory for large images."""
MAX_PADDING = 0.25
"""Partners share a zero-padded block only while the largest has at most this share more descriptors
than the smallest: padding every partner to the largest of all (lego: 146 to 420 keypoints) computed
and searched ~40 % padding."""
PADDING_DISTANCE = 1e30
"""d^2 of a padding row from every query row: never among the two nearest (RootSIFT's d^2 is at most 4), and
finite: +inf in the product gave NaN (0 * inf) where OpenBLAS pads its tiles with zeros."""
NVIDIA_DRIVER = "/proc/driver/nvidia/version"
"""Present where the NVIDIA kernel driver is loaded: without it CUDA cannot be available, and "auto"
decides for the CPU without importing torch."""


class DescriptorMatches(NamedTuple):
    """Matches a[index_a[k]] <-> b[index_b[k]] with Lowe's ratio d1/d2 of each (lower = more distinctive)."""

    index_a: np.ndarray
    index_b: np.ndarray
    ratio: np.ndarray


EMPTY_MATCHES = DescriptorMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


def matching_device(device: Literal["auto", "cpu", "cuda"]) -> str:
    """"cpu" or "cuda"; "auto" is CUDA when torch sees a GPU, asked only when torch is already loaded or an
    NVIDIA driver is present (importing torch costs 0.8 CPU s)."""
    if device != "auto":
        return device
    if "torch" not in sys.modules and not os.path.exists(NVIDIA_DRIVER):
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


class ArrayNamespace(NamedTuple):
    """The array module of the block work (numpy, or torch on `device`) and the few operations where the
    two differ; everything else is called on `xp` with positional axes (`xp.argmin(x, -1)`)."""

    xp: ModuleType
    device: str = "cpu"

    def asarray(self, array: np.ndarray) -> Any:
        """The host array on this namespace's device (numpy: itself)."""
        return array if self.xp is np else self.xp.from_numpy(array).to(self.device)

    def to_numpy(self, values: Any) -> np.ndarray:
        """A host numpy array of this namespace's array (numpy: itself)."""
        return values if self.xp is np else values.cpu().numpy()

    def take_along_last(self, values: Any, index: Any) -> Any:
        """values[..., index[..., k]] along the last axis (numpy's take_along_axis, torch's gather)."""
        return np.take_along_axis(values, index, -1) if self.xp is np else values.gather(-1, index)

    def put_along_last(self, values: Any, index: Any, value: float) -> None:
        """values[..., index[..., k]] = value along the last axis, in place."""
        if self.xp is np:
            np.put_along_axis(values, index, value, -1)
        else:
            values.scatter_(-1, index, value)


NUMPY = ArrayNamespace(np)


def array_namespace(device: str) -> ArrayNamespace:
    """numpy for "cpu", torch for any other device (torch imported only then)."""
    if device == "cpu":
        return NUMPY
    import torch

    return ArrayNamespace(torch, device)


class DescriptorSet(NamedTuple):
    """One image's descriptors as its rows of a partner block: [b, 1, ||b||^2] (N, D + 2) float32, made once
    per image (building them per block was 0.1 of lego's 0.9 matching CPU s)."""

    rows: np.ndarray

    @property
    def descriptors(self) -> np.ndarray:
        """The descriptors (N, D), a view."""
        return self.rows[:, :-2]

    @property
    def squared_norms(self) -> np.ndarray:
        """||d||^2 of each descriptor (N,), a view."""
        return self.rows[:, -1]


def descriptor_set(descriptors: np.ndarray) -> DescriptorSet:
    """The descriptors as float32 with a column of ones and ||d||^2 of each row (`DescriptorSet`)."""
    descriptors = np.ascontiguousarray(descriptors, np.float32)
    rows = np.empty((len(descriptors), descriptors.shape[1] + 2), np.float32)
    rows[:, :-2] = descriptors
    rows[:, -2] = 1.0
    rows[:, -1] = np.einsum("nd,nd->n", descriptors, descriptors)
    return DescriptorSet(rows)


class BlockNeighbours(NamedTuple):
    """Each query row's two nearest partner rows per partner of one padded block, and each partner row's
    nearest query distance (all squared Euclidean, host numpy arrays)."""

    top_distance: np.ndarray        # (A, J, 2) d1^2, d2^2
    top_index: np.ndarray           # (A, J) row of the nearest in partner j
    nearest_a_distance: np.ndarray  # (J, W) per partner row, its nearest query row's d^2


class SmallestTwo(NamedTuple):
    """The two smallest entries along the last axis (..., 2) and the index of the smallest (...)."""

    values: Any
    index: Any


def smallest_two(values: Any, arrays: ArrayNamespace = NUMPY) -> SmallestTwo:
    """The minimum and its index, then the minimum with that one entry at +inf (set in place: `values` is
    overwritten there), each read at its argmin: an argmin took 0.68 ms on a 260x40x300 lego block, an
    `amin` along the rows 1.18 ms, and torch.topk(values, 2, largest=False) three times as long."""
    xp = arrays.xp
    index = xp.argmin(values, -1)[..., None]
    first = arrays.take_along_last(values, index)[..., 0]
    arrays.put_along_last(values, index, float("inf"))
    second = arrays.take_along_last(values, xp.argmin(values, -1)[..., None])[..., 0]
    return SmallestTwo(xp.stack([first, second], -1), index[..., 0])


def query_rows(query: DescriptorSet) -> np.ndarray:
    """[-2 a, ||a||^2, 1] (N, D + 2): its product with `partner_rows` is d^2 = ||a||^2 + ||b||^2 - 2 a.b."""
    ones = np.ones((len(query.rows), 1), np.float32)
    return np.hstack([-2.0 * query.descriptors, query.squared_norms[:, None], ones])


def partner_rows(partners: list[DescriptorSet], width: int) -> np.ndarray:
    """The partners' rows (`DescriptorSet`), each zero-padded to `width` rows ((J * width, D + 2)); a padding
    row is [0, 0, PADDING_DISTANCE]."""
    columns = partners[0].rows.shape[1]
    padding = np.zeros(columns, np.float32)
    padding[-1] = PADDING_DISTANCE
    rows = np.empty((len(partners), width, columns), np.float32)
    for row, b in zip(rows, partners, strict=True):
        row[: len(b.rows)] = b.rows
        row[len(b.rows):] = padding
    return rows.reshape(len(partners) * width, columns)


def nearest_in_block(query: Any, partners: list[DescriptorSet], arrays: ArrayNamespace = NUMPY
                     ) -> BlockNeighbours:
    """d^2 of the query rows (`query_rows`, on `arrays`' device) against the partners zero-padded to one
    block (`partner_rows`), its column minima and its two smallest per partner (`smallest_two`)."""
    xp = arrays.xp
    num_partners, width = len(partners), max(len(b.rows) for b in partners)
    flat_b = arrays.asarray(partner_rows(partners, width))
    num_a = len(query)
    top_distance = np.empty((num_a, num_partners, 2), np.float32)
    top_index = np.empty((num_a, num_partners), np.int64)
    nearest_a_distance = None
    block = max(1, DISTANCE_BLOCK_ELEMENTS // (num_partners * width))
    for start in range(0, num_a, block):
        stop = min(start + block, num_a)
        # The norms are columns of the product (a pass over the block each, 0.45 ms on lego's, saved).
        distance = (query[start:stop] @ flat_b.T).reshape(stop - start, num_partners, width)
        column_minima = xp.amin(distance, 0)
        nearest_a_distance = (column_minima if nearest_a_distance is None
                              else xp.minimum(nearest_a_distance, column_minima))
        # Last: smallest_two overwrites each row's minimum.
        two = smallest_two(distance, arrays)
        top_distance[start:stop] = arrays.to_numpy(two.values)
        top_index[start:stop] = arrays.to_numpy(two.index)
    return BlockNeighbours(top_distance, top_index, arrays.to_numpy(nearest_a_distance))


def size_groups(sizes: list[int], max_padding: float) -> list[list[int]]:
    """Indices of `sizes` in groups, largest first, each group's largest at most (1 + max_padding) times
    its smallest: a group padded to its largest wastes at most that share of its entries."""
    order = sorted(range(len(sizes)), key=lambda k: -sizes[k])
    groups: list[list[int]] = []
    for k in order:
        if groups and sizes[groups[-1][0]] <= (1.0 + max_padding) * sizes[k]:
            groups[-1].append(k)
        else:
            groups.append([k])
    return groups


def match_one_to_many(query: DescriptorSet, partners: list[DescriptorSet], ratio: float, max_distance: float,
                      arrays: ArrayNamespace = NUMPY) -> list[DescriptorMatches]:
    """Per partner b: nearest neighbours a -> b with d1 < ratio * d2 and d1 < max_distance whose b -> a
    nearest neighbour is the same a (Euclidean distances d). Partners of similar size share a padded
    block (`size_groups`, MAX_PADDING)."""
    results = [EMPTY_MATCHES] * len(partners)
    usable = [k for k, b in enumerate(partners) if len(b.rows) >= 2]
    if len(query.rows) < 2 or not usable:
        return results
    rows = arrays.asarray(query_rows(query))
    for group in size_groups([len(partners[k].rows) for k in usable], MAX_PADDING):
        members = [usable[g] for g in group]
        top_distance, top_index, nearest_a_distance = nearest_in_block(
            rows, [partners[k] for k in members], arrays)
        distances = np.sqrt(np.maximum(top_distance, 0.0))
        ratios = distances[..., 0] / np.maximum(distances[..., 1], np.finfo(np.float32).tiny)
        # Mutual: a is as near to its b as b's nearest a is (the column minimum, far cheaper than its
        # argmin; only exactly equal distances, i.e. duplicate descriptors in a, could let two a's through).
        mutual = top_distance[..., 0] <= np.take_along_axis(nearest_a_distance.T, top_index, 0)
        accepted = (ratios < ratio) & (distances[..., 0] < max_distance) & mutual
        for row, k in enumerate(members):
            index_a = np.flatnonzero(accepted[:, row])
            results[k] = DescriptorMatches(index_a, top_index[index_a, row],
                                           ratios[index_a, row].astype(float))
    return results


def match_descriptors(descriptors_a: np.ndarray, descriptors_b: np.ndarray, ratio: float,
                      max_distance: float = np.inf) -> DescriptorMatches:
    """Nearest neighbours a -> b passing d1 < ratio * d2 (and d1 < max_distance) whose b -> a nearest
    neighbour is the same a."""
    return match_one_to_many(descriptor_set(descriptors_a), [descriptor_set(descriptors_b)], ratio,
                             max_distance)[0]
