"""Descriptor matching: nearest neighbours by batched distance matrices in torch, Lowe's ratio test and
a mutual (cross) check.

One image is matched against all its partner images at once: the partners' descriptors are stacked
into a zero-padded (J, F, 128) block (padding at infinite distance), and the squared distances
||a||^2 + ||b||^2 - 2 a.b come from one matrix product per block of query rows, on the CPU or CUDA.
"""

from __future__ import annotations

from collections import defaultdict
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


def match_one_to_many(descriptors_a: np.ndarray, partners: list[np.ndarray], ratio: float,
                      device: torch.device = torch.device("cpu")) -> list[DescriptorMatches]:
    """Per partner b: nearest neighbours a -> b with d1 < ratio * d2 whose b -> a nearest is the same a."""
    if len(descriptors_a) < 2:
        return [EMPTY_MATCHES] * len(partners)
    usable = [k for k, b in enumerate(partners) if len(b) >= 2]
    results = [EMPTY_MATCHES] * len(partners)
    if not usable:
        return results
    width = max(len(partners[k]) for k in usable)
    stacked = torch.zeros((len(usable), width, descriptors_a.shape[1]), dtype=torch.float32, device=device)
    squared_b = torch.full((len(usable), width), float("inf"), device=device)
    for row, k in enumerate(usable):
        b = torch.as_tensor(partners[k], dtype=torch.float32, device=device)
        stacked[row, : len(b)] = b
        squared_b[row, : len(b)] = (b * b).sum(dim=1)
    a = torch.as_tensor(descriptors_a, dtype=torch.float32, device=device)
    squared_a = (a * a).sum(dim=1)
    flat_b = stacked.reshape(-1, stacked.shape[-1])

    num_a = len(a)
    top_distance = torch.empty((num_a, len(usable), 2), device=device)
    top_index = torch.empty((num_a, len(usable)), dtype=torch.int64, device=device)
    nearest_a_distance = torch.full((len(usable), width), float("inf"), device=device)
    nearest_a = torch.zeros((len(usable), width), dtype=torch.int64, device=device)
    block = max(1, DISTANCE_BLOCK_ELEMENTS // max(1, flat_b.shape[0]))
    for start in range(0, num_a, block):
        stop = min(start + block, num_a)
        distance = (squared_a[start:stop, None] + squared_b.reshape(1, -1)
                    - 2.0 * (a[start:stop] @ flat_b.T)).reshape(stop - start, len(usable), width)
        top = torch.topk(distance, 2, dim=2, largest=False)
        top_distance[start:stop] = top.values
        top_index[start:stop] = top.indices[:, :, 0]
        block_min, block_arg = distance.min(dim=0)
        better = block_min < nearest_a_distance
        nearest_a_distance = torch.where(better, block_min, nearest_a_distance)
        nearest_a = torch.where(better, block_arg + start, nearest_a)

    distances = top_distance.clamp_min(0.0).sqrt()
    ratios = distances[..., 0] / distances[..., 1].clamp_min(torch.finfo(torch.float32).tiny)
    mutual = torch.gather(nearest_a.T, 0, top_index) == torch.arange(num_a, device=device)[:, None]
    accepted = (distances[..., 0] < ratio * distances[..., 1]) & mutual
    accepted, top_index, ratios = accepted.cpu().numpy(), top_index.cpu().numpy(), ratios.cpu().numpy()
    for row, k in enumerate(usable):
        index_a = np.flatnonzero(accepted[:, row])
        results[k] = DescriptorMatches(index_a, top_index[index_a, row], ratios[index_a, row].astype(float))
    return results


def match_descriptors(descriptors_a: np.ndarray, descriptors_b: np.ndarray, ratio: float,
                      device: torch.device = torch.device("cpu")) -> DescriptorMatches:
    """Nearest neighbours a -> b passing d1 < ratio * d2 whose b -> a nearest neighbour is the same a."""
    return match_one_to_many(descriptors_a, [descriptors_b], ratio, device)[0]


def match_pairs(descriptors: list[np.ndarray], pairs: list[tuple[int, int]], ratio: float,
                device: torch.device = torch.device("cpu")) -> dict[tuple[int, int], DescriptorMatches]:
    """Matches of every pair (i, j), each image i matched against all its partners j in one batch."""
    partners_of: dict[int, list[int]] = defaultdict(list)
    for i, j in pairs:
        partners_of[i].append(j)
    matches = {}
    for i, partners in partners_of.items():
        for j, result in zip(partners, match_one_to_many(descriptors[i], [descriptors[j] for j in partners],
                                                         ratio, device), strict=True):
            matches[(i, j)] = result
    return matches
