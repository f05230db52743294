"""Descriptor matching: nearest neighbours by batched distance matrices in torch, Lowe's ratio test and
a mutual (cross) check.

One image is matched against all its partner images at once: the partners' descriptors are stacked
into a zero-padded (J, F, 128) block (padding at infinite distance), and the squared distances
||a||^2 + ||b||^2 - 2 a.b come from one matrix product per block of query rows, on the CPU or CUDA.
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


def match_one_to_many(query: DescriptorSet, partners: list[DescriptorSet], ratio: float, max_distance: float,
                      device: torch.device = torch.device("cpu")) -> list[DescriptorMatches]:
    """Per partner b: nearest neighbours a -> b with d1 < ratio * d2 and d1 < max_distance whose b -> a
    nearest neighbour is the same a (Euclidean distances d)."""
    results = [EMPTY_MATCHES] * len(partners)
    usable = [k for k, b in enumerate(partners) if len(b.descriptors) >= 2]
    if len(query.descriptors) < 2 or not usable:
        return results
    # Padding: zero descriptors at infinite distance (their squared norm is +inf).
    num_partners, width = len(usable), max(len(partners[k].descriptors) for k in usable)
    stacked = np.zeros((num_partners, width, query.descriptors.shape[1]), np.float32)
    squared_b = np.full((num_partners, width), np.inf, np.float32)
    for row, k in enumerate(usable):
        stacked[row, : len(partners[k].descriptors)] = partners[k].descriptors
        squared_b[row, : len(partners[k].descriptors)] = partners[k].squared_norms
    flat_b = torch.from_numpy(stacked.reshape(num_partners * width, -1)).to(device)
    flat_squared_b = torch.from_numpy(squared_b.reshape(1, -1)).to(device)
    a, squared_a = (torch.from_numpy(array).to(device) for array in query)
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
        top = torch.topk(distance, 2, dim=2, largest=False)
        top_distance[start:stop] = top.values
        top_index[start:stop] = top.indices[:, :, 0]
        nearest_a_distance = torch.minimum(nearest_a_distance, distance.amin(dim=0))

    distances = top_distance.clamp_min(0.0).sqrt()
    ratios = distances[..., 0] / distances[..., 1].clamp_min(torch.finfo(torch.float32).tiny)
    # Mutual: a is as near to its b as b's nearest a is (the column minimum, far cheaper than its argmin;
    # only exactly equal distances, i.e. duplicate descriptors in a, could let two a's through).
    mutual = top_distance[..., 0] <= torch.gather(nearest_a_distance.T, 0, top_index)
    accepted = (ratios < ratio) & (distances[..., 0] < max_distance) & mutual
    accepted, top_index, ratios = accepted.cpu().numpy(), top_index.cpu().numpy(), ratios.cpu().numpy()
    for row, k in enumerate(usable):
        index_a = np.flatnonzero(accepted[:, row])
        results[k] = DescriptorMatches(index_a, top_index[index_a, row], ratios[index_a, row].astype(float))
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
