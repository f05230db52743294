"""Pair selection for a video's frames: each frame with its next frames, plus loop closures by retrieval."""

from __future__ import annotations

import numpy as np

from estimation.config import SiftConfig
from estimation.features.pairs import candidate_pairs, loop_closure_pairs, sequential_pairs


def circle_descriptors(count: int) -> np.ndarray:
    """Unit global descriptors of frames around a closed loop: frame i looks like i +- 1, and the last
    frames look like the first ones."""
    angles = 2 * np.pi * np.arange(count) / count
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def test_loop_closures_join_the_end_of_a_loop_to_its_start_and_never_repeat_the_window():
    order = list(range(40))
    pairs = loop_closure_pairs(circle_descriptors(40), order, window=5, neighbours=2)
    assert (0, 39) in pairs and (1, 39) in pairs and (0, 38) in pairs
    assert all(abs(i - j) > 5 for i, j in pairs)
    assert all(min(abs(i - j), 40 - abs(i - j)) <= 8 for i, j in pairs)   # near along the loop


def test_video_pairs_are_the_sequential_window_plus_loop_closures_in_name_order():
    rng = np.random.default_rng(0)
    count = 30
    # Each frame's descriptors: words of its place on the loop (frame i shares them with i +- 1), so the
    # VLAD of the last frames resembles the first ones'.
    places = [rng.normal(size=(40, 128)).astype(np.float32) for _ in range(12)]
    place = [round(12 * i / count) for i in range(count)]
    descriptors = [np.concatenate([places[p % 12], places[(p + 1) % 12]]) for p in place]
    names = [f"{number:06d}.jpg" for number in range(0, 3 * count, 3)][::-1]   # listed backwards
    descriptors = descriptors[::-1]
    config = SiftConfig(pair_selection="video", sequential_neighbours=4, loop_closure_neighbours=2,
                        vocabulary_size=8)
    pairs = set(candidate_pairs(names, descriptors, config))
    order = list(range(count))[::-1]                                     # frame number order
    sequential = sequential_pairs(order, 4)
    assert sequential <= pairs
    closures = pairs - sequential
    assert closures and len(closures) <= 2 * count
    position = {index: k for k, index in enumerate(order)}
    assert any(abs(position[i] - position[j]) >= count - 5 for i, j in closures)  # end joined to start
    assert len(pairs) < count * (count - 1) // 2                               # not exhaustive
