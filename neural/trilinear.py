"""Trilinear interpolation of dense voxel grids, split over the CPU's threads.

`F.grid_sample`'s CPU kernels (forward and backward) parallelize over the batch only, so one grid looked up at
N points runs on one thread. Here the points are split into one batch entry per thread, with the grid
expanded (not copied) to match. The backward pass then writes one gradient per entry, summed afterwards;
where those copies would be large, a lookup that needs the grid's gradient is split into fewer entries.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

#: The largest per-thread gradient copies (bytes, all threads) a split lookup may allocate. glibc hands
#: blocks above 32 MiB (its largest mmap threshold) back to the system when freed, so larger copies are
#: page-faulted in anew at every step: the fast model's 3-channel colour grid at 128^3 (2 x 25 MB) took
#: 29 ms forward + backward split against 11.5 ms unsplit (bench_nerf.py, benchmarks/RESULTS.md).
MAX_SPLIT_GRADIENT_BYTES = 32 * 2**20


def trilinear(grid: Tensor, coordinates: Tensor) -> Tensor:
    """Values (N,C) of a (1,C,X,Y,Z) grid at points (N,3) in [-1,1]^3 (x along X: -1 the first vertex, 1 the
    last); zero outside."""
    parts = lookup_parts(grid)
    num_points, channels = coordinates.shape[0], grid.shape[1]
    per_part = -(-num_points // parts)
    padded = F.pad(coordinates, (0, 0, 0, per_part * parts - num_points))
    # grid_sample's last axis is (W, H, D) = (Z, Y, X) for a (1,C,X,Y,Z) grid.
    batched = padded.flip(-1).reshape(parts, 1, 1, per_part, 3)
    values = F.grid_sample(
        grid.expand(parts, *grid.shape[1:]), batched, mode="bilinear", align_corners=True
    )  # (parts, C, 1, 1, per_part)
    return values.reshape(parts, channels, per_part).transpose(1, 2).reshape(-1, channels)[:num_points]


def lookup_parts(grid: Tensor) -> int:
    """How many batch entries a lookup of the grid is split into: one per CPU thread, but where the backward
    pass makes one gradient copy per entry, no more than MAX_SPLIT_GRADIENT_BYTES of copies (at least 1);
    1 on other devices."""
    if grid.device.type != "cpu":
        return 1
    threads = torch.get_num_threads()
    if not (grid.requires_grad and torch.is_grad_enabled()):
        return threads
    copies_that_fit = MAX_SPLIT_GRADIENT_BYTES // (grid.numel() * grid.element_size())
    return max(1, min(threads, copies_that_fit))
