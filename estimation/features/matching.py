"""Descriptor matching: nearest neighbours by batched distance matrices in torch, Lowe's ratio test and
a mutual (cross) check.

One image is matched against all its partner images at once: the partners' descriptors are stacked
into zero-padded (J, F, 128) blocks of partners of similar size (padding at infinite distance), and the
squared distances ||a||^2 + ||b||^2 - 2 a.b come from one matrix product per block of query rows, on
the CPU or CUDA.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import NamedTuple

import numpy as np
import torch

DISTANCE_BLOCK_ELEMENTS = 1 << 24
"""Entries of the distance matrix held at once (64 MiB of float32): bounds memory for large images."""
MAX_PADDING = 0.25
"""Partners share a zero-padded block only while the largest has at most this share more descriptors
than the smallest: padding every partner to the largest of all (lego: 146 to 420 keypoints) computed
and searched ~40 % padding."""


class DescriptorMatches(NamedTuple):
    """Matches a[index_a[k]] <-> b[index_b[k]] with Lowe's ratio d1/d2 of each (lower = more distinctive)."""

    index_a: np.ndarray
    index_b: np.ndarray
    ratio: np.ndarray


EMPTY_MATCHES = DescriptorMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))


def matching_device(device: str) -> torch.device:
    """torch device for "cpu", "cuda" or "auto" (CUDA when available)."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(device)


class DescriptorSet(NamedTuple):
    """One image's descriptors (N, D) float32 and their squared norms (N,), as numpy arrays."""

    descriptors: np.ndarray
    squared_norms: np.ndarray


def descriptor_set(descriptors: np.ndarray) -> DescriptorSet:
    descriptors = np.ascontiguousarray(descriptors, np.float32)
    return DescriptorSet(descriptors, np.einsum("nd,nd->n", descriptors, descriptors))


class BlockNeighbours(NamedTuple):
    """Each query row's two nearest partner rows per partner of one padded block, and each partner row's
    nearest query distance (all squared Euclidean, torch tensors)."""

    top_distance: torch.Tensor        # (A, J, 2) d1^2, d2^2
    top_index: torch.Tensor           # (A, J) row of the nearest in partner j
    nearest_a_distance: torch.Tensor  # (J, W) per partner row, its nearest query row's d^2


class SmallestTwo(NamedTuple):
    """The two smallest entries along the last axis (..., 2) and the index of the smallest (...)."""

    values: torch.Tensor
    index: torch.Tensor


def argmin_last(values: torch.Tensor) -> torch.Tensor:
    """Index of the minimum along the last axis; on the CPU by numpy (a zero-copy view), whose argmin took
    0.81 ms on a 260x40x300 lego block against 1.94 ms for torch's min with its index (4.8 for argmin)."""
    if values.device.type == "cpu":
        return torch.from_numpy(values.numpy().argmin(axis=-1))
    return values.argmin(dim=-1)


def smallest_two(values: torch.Tensor) -> SmallestTwo:
    """The minimum and its index, then the minimum with that one entry at +inf (set in place: `values` is
    overwritten there). The same values as torch.topk(values, 2, largest=False), in a third of its time on
    lego's blocks (an argmin and an amin reduction against topk's per-row selection)."""
    index = argmin_last(values)[..., None]
    first = torch.gather(values, -1, index)[..., 0]
    values.scatter_(-1, index, float("inf"))
    return SmallestTwo(torch.stack([first, values.amin(dim=-1)], dim=-1), index[..., 0])


def nearest_in_block(a: torch.Tensor, squared_a: torch.Tensor, partners: list[DescriptorSet],
                     device: torch.device) -> BlockNeighbours:
    """d^2 = ||a||^2 + ||b||^2 - 2 a.b of the query rows against the partners zero-padded to one block
    (padding at d^2 = +inf), its column minima and its two smallest per partner (`smallest_two`)."""
    num_partners, width = len(partners), max(len(b.descriptors) for b in partners)
    stacked = np.zeros((num_partners, width, a.shape[1]), np.float32)
    squared_b = np.full((num_partners, width), np.inf, np.float32)
    for row, b in enumerate(partners):
        stacked[row, : len(b.descriptors)] = b.descriptors
        squared_b[row, : len(b.descriptors)] = b.squared_norms
    flat_b = torch.from_numpy(stacked.reshape(num_partners * width, -1)).to(device)
    flat_squared_b = torch.from_numpy(squared_b.reshape(1, -1)).to(device)
    num_a = len(a)
    top_distance = torch.empty((num_a, num_partners, 2), device=device)
    top_index = torch.empty((num_a, num_partners), dtype=torch.int64, device=device)
    nearest_a_distance = torch.full((num_partners, width), float("inf"), device=device)
    block = max(1, DISTANCE_BLOCK_ELEMENTS // (num_partners * width))
    for start in range(0, num_a, block):
        stop = min(start + block, num_a)
        # ||b||^2 - 2 a.b in the product, + ||a||^2 in place: no second block-sized temporary.
        distance = torch.addmm(flat_squared_b, a[start:stop], flat_b.T, alpha=-2.0)
        distance = distance.add_(squared_a[start:stop, None]).reshape(stop - start, num_partners, width)
        nearest_a_distance = torch.minimum(nearest_a_distance, distance.amin(dim=0))
        # Last: smallest_two overwrites each row's minimum.
        top_distance[start:stop], top_index[start:stop] = smallest_two(distance)
    return BlockNeighbours(top_distance, top_index, nearest_a_distance)


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
                      device: torch.device = torch.device("cpu")) -> list[DescriptorMatches]:
    """Per partner b: nearest neighbours a -> b with d1 < ratio * d2 and d1 < max_distance whose b -> a
    nearest neighbour is the same a (Euclidean distances d). Partners of similar size share a padded
    block (`size_groups`, MAX_PADDING)."""
    results = [EMPTY_MATCHES] * len(partners)
    usable = [k for k, b in enumerate(partners) if len(b.descriptors) >= 2]
    if len(query.descriptors) < 2 or not usable:
        return results
    a, squared_a = (torch.from_numpy(array).to(device) for array in query)
    for group in size_groups([len(partners[k].descriptors) for k in usable], MAX_PADDING):
        members = [usable[g] for g in group]
        top_distance, top_index, nearest_a_distance = nearest_in_block(
            a, squared_a, [partners[k] for k in members], device)
        distances = top_distance.clamp_min(0.0).sqrt()
        ratios = distances[..., 0] / distances[..., 1].clamp_min(torch.finfo(torch.float32).tiny)
        # Mutual: a is as near to its b as b's nearest a is (the column minimum, far cheaper than its
        # argmin; only exactly equal distances, i.e. duplicate descriptors in a, could let two a's through).
        mutual = top_distance[..., 0] <= torch.gather(nearest_a_distance.T, 0, top_index)
        accepted = (ratios < ratio) & (distances[..., 0] < max_distance) & mutual
        accepted, top_index, ratios = accepted.cpu().numpy(), top_index.cpu().numpy(), ratios.cpu().numpy()
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


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op CPU threads set to `count` inside the block, restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def match_pairs(descriptors: list[np.ndarray], pairs: list[tuple[int, int]], ratio: float,
                max_distance: float = np.inf, device: torch.device = torch.device("cpu"),
                cpu_threads: int = 1, workers: int = 1) -> dict[tuple[int, int], DescriptorMatches]:
    """Matches of every pair (i, j), each image i matched against all its partners j in one batch
    (`cpu_threads` torch threads each), the images i in `workers` threads at once (torch releases the GIL
    in its kernels)."""
    sets = [descriptor_set(d) for d in descriptors]
    partners_of: dict[int, list[int]] = defaultdict(list)
    for i, j in pairs:
        partners_of[i].append(j)

    def match_image(i: int) -> list[DescriptorMatches]:
        return match_one_to_many(sets[i], [sets[j] for j in partners_of[i]], ratio, max_distance, device)

    matches = {}
    with torch_threads(cpu_threads), ThreadPoolExecutor(workers) as threads:
        for i, results in zip(partners_of, threads.map(match_image, partners_of), strict=True):
            matches.update({(i, j): result for j, result in zip(partners_of[i], results, strict=True)})
    return matches
