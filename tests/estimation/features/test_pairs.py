"""Pair selection: exhaustive for small sets, else retrieval + sequence neighbours in natural order."""

from __future__ import annotations

import cv2
import numpy as np

from estimation.config import SiftConfig
from estimation.features.pairs import (
    candidate_pairs,
    exhaustive_pairs,
    natural_key,
    sequence_order,
    sequential_pairs,
)
from estimation.features.sift import detect_features


def test_natural_order_puts_2_before_10():
    names = ["r_10.png", "r_2.png", "r_1.png", "r_100.png", "R_3.png"]
    assert sorted(names, key=natural_key) == ["r_1.png", "r_2.png", "R_3.png", "r_10.png", "r_100.png"]


def test_sequence_neighbours_follow_the_numbers_whatever_the_listing_order():
    numbers = np.random.default_rng(0).permutation(np.arange(1, 41))
    names = [f"frame_{n}.png" for n in numbers]                 # shuffled listing
    order = sequence_order(names)
    assert [names[i] for i in order] == [f"frame_{n}.png" for n in range(1, 41)]
    index_of = {n: k for k, n in enumerate(numbers)}
    expected = {tuple(sorted((index_of[n], index_of[n + d])))
                for n in range(1, 41) for d in (1, 2) if n + d <= 40}
    assert sequential_pairs(order, 2) == expected


def test_a_lexicographic_listing_is_never_used_as_a_sequence():
    names = sorted(f"r_{n}.png" for n in range(30))            # r_0, r_1, r_10, r_11, ..., r_2, r_20, ...
    pairs = sequential_pairs(sequence_order(names), 1)
    index = {name: k for k, name in enumerate(names)}
    assert (index["r_1.png"], index["r_2.png"]) in {tuple(sorted(p)) for p in pairs}
    assert tuple(sorted((index["r_1.png"], index["r_10.png"]))) not in pairs
    assert sequence_order(["left.png", "right.png"]) is None


def test_small_sets_match_every_pair():
    assert candidate_pairs(["a.png", "b.png", "c.png"], [np.zeros((0, 128))] * 3, SiftConfig()) == (
        exhaustive_pairs(3)) == [(0, 1), (0, 2), (1, 2)]


def textured_views(num_scenes: int, views: int, seed: int) -> tuple[list[np.ndarray], list[int]]:
    """Each scene a smooth random texture, seen in `views` similarity warps (rotation, scale, shift)."""
    rng = np.random.default_rng(seed)
    images, scene_of = [], []
    for scene in range(num_scenes):
        texture = cv2.GaussianBlur(rng.normal(size=(240, 240)), (0, 0), 3)
        texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        for _ in range(views):
            warp = cv2.getRotationMatrix2D((120, 120), rng.uniform(-15, 15), rng.uniform(0.9, 1.1))
            warp[:, 2] += rng.uniform(-10, 10, 2)
            gray = cv2.warpAffine(texture, warp, (200, 200), borderMode=cv2.BORDER_REFLECT)
            images.append(np.repeat(gray[:, :, None], 3, axis=2))
            scene_of.append(scene)
    return images, scene_of


def test_retrieval_pairs_each_view_with_the_other_views_of_its_scene():
    images, scene_of = textured_views(num_scenes=4, views=3, seed=1)
    order = np.random.default_rng(2).permutation(len(images))   # listing order says nothing
    descriptors = [detect_features(images[k], SiftConfig(max_features=300)).descriptors for k in order]
    scenes = np.array(scene_of)[order]
    config = SiftConfig(exhaustive_up_to=10, retrieval_neighbours=2, sequential_neighbours=0,
                        vocabulary_size=16)
    pairs = candidate_pairs([f"view_{k}.png" for k in range(len(order))], descriptors, config)
    same_scene = {(i, j) for i, j in exhaustive_pairs(len(order)) if scenes[i] == scenes[j]}
    assert set(pairs) == same_scene                              # 2 neighbours = the scene's other views
