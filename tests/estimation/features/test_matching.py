"""Batched descriptor matching: ratio test, mutual check, agreement with brute force per pair, and the same
matches from numpy and torch."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from estimation.features.matching import (
    DISTANCE_BLOCK_ELEMENTS,
    NUMPY,
    ArrayNamespace,
    descriptor_set,
    match_descriptors,
    match_one_to_many,
    size_groups,
    smallest_two,
)

TORCH = ArrayNamespace(torch, "cpu")


def unit(vector: np.ndarray) -> np.ndarray:
    return (vector / np.linalg.norm(vector)).astype(np.float32)


def test_the_ratio_test_drops_a_match_with_two_equally_close_candidates():
    rng = np.random.default_rng(0)
    a = np.stack([unit(rng.normal(size=128)) for _ in range(3)])
    b = np.concatenate([a + 0.01, [a[0] + 0.012]]).astype(np.float32)   # a[0] has two near twins in b
    matches = match_descriptors(a, b, ratio=0.8)
    np.testing.assert_array_equal(matches.index_a, [1, 2])
    np.testing.assert_array_equal(matches.index_b, [1, 2])
    assert np.all(matches.ratio < 0.8)


def test_the_mutual_check_keeps_only_the_match_both_sides_agree_on():
    rng = np.random.default_rng(1)
    base = unit(rng.normal(size=128))
    far = [unit(rng.normal(size=128)) for _ in range(3)]
    # a[0] and a[1] both have b[0] as their clear nearest neighbour; b[0]'s nearest is a[1].
    a = np.stack([unit(base + 0.08 * far[0]), unit(base + 0.01 * far[1])])
    b = np.stack([base, far[2]])
    matches = match_descriptors(a, b, ratio=0.9)
    np.testing.assert_array_equal(matches.index_a, [1])
    np.testing.assert_array_equal(matches.index_b, [0])


@pytest.mark.parametrize("arrays", [NUMPY, TORCH], ids=["numpy", "torch"])
def test_the_two_smallest_per_row_are_the_sorted_first_two_and_a_repeated_minimum_counts_twice(arrays):
    values = np.random.default_rng(3).random((4, 5, 30)).astype(np.float32)
    values[0, 0, [4, 17]] = -1.0                                  # a minimum that occurs twice
    expected = np.sort(values, axis=-1)[..., :2]
    two = smallest_two(arrays.asarray(values.copy()), arrays)
    np.testing.assert_array_equal(arrays.to_numpy(two.values), expected)
    index = arrays.to_numpy(two.index)
    np.testing.assert_array_equal(index[1:], np.argmin(values[1:], axis=-1))
    assert index[0, 0] in (4, 17)


def test_too_few_descriptors_give_no_matches():
    one, five = np.zeros((1, 128), np.float32), np.zeros((5, 128), np.float32)
    assert len(match_descriptors(one, five, 0.8).ratio) == 0
    assert len(match_descriptors(five, one, 0.8).ratio) == 0


def brute_force(a: np.ndarray, b: np.ndarray, ratio: float) -> set[tuple[int, int]]:
    """OpenCV's brute-force kNN with the same ratio test and cross check, as the reference."""
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    nearest_a_of_b = {m.queryIdx: m.trainIdx for m in matcher.match(b, a)}
    return {(best.queryIdx, best.trainIdx) for best, second in matcher.knnMatch(a, b, k=2)
            if best.distance < ratio * second.distance and nearest_a_of_b[best.trainIdx] == best.queryIdx}


def random_images(rng: np.random.Generator, counts: tuple[int, ...]) -> list[np.ndarray]:
    """Descriptor sets of the given sizes sharing noisy copies of up to 150 common rows, shuffled."""
    shared = rng.normal(size=(150, 128))
    images = []
    for count in counts:
        rows = np.concatenate([shared[: min(count, 150)], rng.normal(size=(max(count - 150, 0), 128))])
        noisy = rows + rng.normal(0, 0.3, rows.shape)
        images.append(np.abs(noisy[rng.permutation(count)]).astype(np.float32))
    return images


def match_each_image_with_the_later_ones(images: list[np.ndarray], arrays: ArrayNamespace
                                         ) -> dict[tuple[int, int], set[tuple[int, int]]]:
    """Index pairs (a, b) of every image pair (i, j > i), image i matched against all its partners at once."""
    sets = [descriptor_set(d) for d in images]
    found = {}
    for i in range(len(images)):
        partners = list(range(i + 1, len(images)))
        for j, result in zip(partners, match_one_to_many(sets[i], [sets[j] for j in partners], 0.8, np.inf,
                                                         arrays), strict=True):
            found[(i, j)] = set(zip(result.index_a.tolist(), result.index_b.tolist(), strict=True))
    return found


def test_batched_matching_of_many_pairs_equals_brute_force_pair_by_pair(monkeypatch):
    images = random_images(np.random.default_rng(2), (300, 180, 250, 2, 90))   # uneven: padding is exercised
    # A small block forces several blocks of query rows per image.
    monkeypatch.setattr("estimation.features.matching.DISTANCE_BLOCK_ELEMENTS", DISTANCE_BLOCK_ELEMENTS >> 8)
    for (i, j), found in match_each_image_with_the_later_ones(images, NUMPY).items():
        enough = min(len(images[i]), len(images[j])) >= 2
        expected = brute_force(images[i], images[j], 0.8) if enough else set()
        assert found == expected
        assert len(expected) > 20 or 3 in (i, j)                  # image 3 has only two descriptors


def test_numpy_and_torch_find_the_same_matches(monkeypatch):
    """One matcher for both namespaces: torch (CUDA on a GPU machine, its CPU here) finds numpy's matches."""
    images = random_images(np.random.default_rng(4), (260, 400, 120, 330, 150, 290))
    monkeypatch.setattr("estimation.features.matching.DISTANCE_BLOCK_ELEMENTS", DISTANCE_BLOCK_ELEMENTS >> 6)
    in_numpy = match_each_image_with_the_later_ones(images, NUMPY)
    assert sum(map(len, in_numpy.values())) > 500
    assert match_each_image_with_the_later_ones(images, TORCH) == in_numpy


def test_partners_are_grouped_by_size_so_that_padding_stays_bounded():
    sizes = [420, 146, 300, 410, 150, 260, 2, 340]
    groups = size_groups(sizes, max_padding=0.25)
    assert sorted(k for group in groups for k in group) == list(range(len(sizes)))   # each partner once
    for group in groups:
        assert max(sizes[k] for k in group) <= 1.25 * min(sizes[k] for k in group)
    assert groups[0] == [0, 3, 7]                                # largest first, greedily joined
    assert size_groups(sizes, max_padding=10.0) == [[0, 3, 7, 2, 5, 4, 1], [6]]
