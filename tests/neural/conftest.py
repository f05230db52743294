"""Fixtures for the NeRF tests: one torch thread (the suite runs in parallel workers), tiny datasets."""

from pathlib import Path

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def single_torch_thread():
    # Parallel test workers on a small shared machine: more threads than cores makes torch far slower.
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def tiny_npz(shared_data: Path, tmp_path_factory) -> Path:
    """Six lego_tiny views (five train, one val) box-downsampled 5x to 20x20, as a tiny-NeRF file."""
    source = np.load(shared_data / "lego_tiny.npz")
    picks = [0, 10, 20, 30, 40, 80]
    images = source["images"][picks].reshape(6, 20, 5, 20, 5, 3).mean(axis=(2, 4)).astype(np.float32)
    path = tmp_path_factory.mktemp("tiny") / "tiny.npz"
    np.savez(
        path,
        images=images,
        poses=source["poses"][picks],
        focal=np.float64(source["focal"]) / 5.0,
        split=np.array([0, 0, 0, 0, 0, 1]),
    )
    return path


#: A vanilla model small enough to train a few steps in a test.
TINY_VANILLA = {"width": 32, "colour_width": 16, "coarse_samples": 16, "fine_samples": 16}
