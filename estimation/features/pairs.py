"""Which image pairs to match: all of them for up to `exhaustive_up_to` images; beyond, each image's most
similar images by retrieval (VLAD over its SIFT descriptors, with a k-means vocabulary of the set's own
descriptors) plus, when the file names are numbered, its next images in natural order (2 before 10).

Order is only ever taken from natural-sorted names: a window over lexicographic names
(r_0, r_1, r_10, r_100, ...) pairs images that are far apart in the capture.
"""

from __future__ import annotations

import re

import cv2
import numpy as np

from estimation.config import SiftConfig

VOCABULARY_TRAINING_DESCRIPTORS = 20_000
"""At most this many descriptors (sampled evenly over the images) train the k-means vocabulary: about 300 a
word. k-means' time grows with them, its words barely: a 270-image set's 69,488 took 2.0 s on one core,
20,000 of them 0.8 s (no worker shares this step); on lego, 20,000 and all 23,155 give the same retrieval
recall (benchmarks/bench_features.py --vocabulary-descriptors 20000,0 --turned)."""
KMEANS_ITERATIONS = 20
KMEANS_SEED = 0
_NUMBER = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple:
    """Sort key splitting digit runs out as numbers: "r_2.png" < "r_10.png"."""
    parts = _NUMBER.split(name)
    return tuple((1, int(part), "") if part.isdigit() else (0, 0, part.lower()) for part in parts)


def sequence_order(names: list[str]) -> list[int] | None:
    """Image indices in natural name order when every name carries a number (a sequence), else None."""
    if not names or not all(_NUMBER.search(name) for name in names):
        return None
    return sorted(range(len(names)), key=lambda index: natural_key(names[index]))


def exhaustive_pairs(num_images: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(num_images) for j in range(i + 1, num_images)]


def sequential_pairs(order: list[int], neighbours: int) -> set[tuple[int, int]]:
    """Each image with its next `neighbours` images along `order`."""
    return {(min(a, b), max(a, b)) for k, a in enumerate(order) for b in order[k + 1: k + 1 + neighbours]}


def train_vocabulary(descriptors: list[np.ndarray], size: int,
                     max_descriptors: int = VOCABULARY_TRAINING_DESCRIPTORS) -> np.ndarray:
    """(size, D) k-means centres (cv2.kmeans, k-means++) of up to `max_descriptors` rows, sampled evenly."""
    everything = np.concatenate([d for d in descriptors if len(d)]).astype(np.float32)
    if len(everything) > max_descriptors:
        sample = np.linspace(0, len(everything) - 1, max_descriptors).astype(int)
        everything = everything[sample]
    size = min(size, len(everything))
    cv2.setRNGSeed(KMEANS_SEED)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, KMEANS_ITERATIONS, 1e-4)
    _, _, centres = cv2.kmeans(everything, size, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    return centres


def l2_normalized(vectors: np.ndarray, axis: int = -1) -> np.ndarray:
    """v / max(||v||, 1e-12) along `axis` (a zero vector stays zero)."""
    return vectors / np.maximum(np.linalg.norm(vectors, axis=axis, keepdims=True), 1e-12)


def vlad(descriptors: np.ndarray, vocabulary: np.ndarray) -> np.ndarray:
    """VLAD: per word, the sum of (descriptor - centre) over the descriptors nearest to it; each word's
    block L2-normalized (intra-normalization), signed square root, then the whole vector L2-normalized."""
    words, dimension = vocabulary.shape
    if len(descriptors) == 0:
        return np.zeros(words * dimension, np.float32)
    d = np.asarray(descriptors, np.float32)
    centres = np.asarray(vocabulary, np.float32)
    # argmin_c ||d - c||^2 = argmin_c ||c||^2 - 2 d.c (||d||^2 is the same for every word).
    nearest = np.argmin(np.einsum("cd,cd->c", centres, centres) - 2.0 * d @ centres.T, axis=1)
    residual_sums = np.zeros_like(centres)
    np.add.at(residual_sums, nearest, d - centres[nearest])
    flat = l2_normalized(residual_sums).ravel()
    return l2_normalized(np.sign(flat) * np.sqrt(np.abs(flat)))


def retrieval_pairs(global_descriptors: np.ndarray, neighbours: int) -> set[tuple[int, int]]:
    """Each image with its `neighbours` most similar images by the dot product of global descriptors."""
    similarity = global_descriptors @ global_descriptors.T
    np.fill_diagonal(similarity, -np.inf)
    k = min(neighbours, len(similarity) - 1)
    nearest = np.argpartition(-similarity, k - 1, axis=1)[:, :k]
    return {(min(i, int(j)), max(i, int(j))) for i in range(len(similarity)) for j in nearest[i]}


def loop_closure_pairs(global_descriptors: np.ndarray, order: list[int], window: int, neighbours: int
                       ) -> set[tuple[int, int]]:
    """Each image with its `neighbours` most similar images (dot product of global descriptors) among those
    more than `window` places away along `order`: the pairs a sequence's window misses when it returns."""
    position = np.empty(len(order), int)
    position[order] = np.arange(len(order))
    similarity = global_descriptors @ global_descriptors.T
    similarity[np.abs(position[:, None] - position[None, :]) <= window] = -np.inf
    pairs: set[tuple[int, int]] = set()
    for i, row in enumerate(similarity):
        for j in np.argsort(-row)[:neighbours]:
            if np.isfinite(row[j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return pairs


def video_pairs(names: list[str], descriptors: list[np.ndarray], config: SiftConfig
                ) -> set[tuple[int, int]]:
    """Frames of one video, numbered in order: each with its `sequential_neighbours` next frames, plus its
    `loop_closure_neighbours` most similar frames (VLAD) beyond that window."""
    order = sequence_order(names) or list(range(len(names)))
    pairs = sequential_pairs(order, config.sequential_neighbours)
    if config.loop_closure_neighbours and len(names) > config.sequential_neighbours + 1:
        vocabulary = train_vocabulary(descriptors, config.vocabulary_size)
        pairs |= loop_closure_pairs(np.stack([vlad(d, vocabulary) for d in descriptors]), order,
                                    config.sequential_neighbours, config.loop_closure_neighbours)
    return pairs


def candidate_pairs(names: list[str], descriptors: list[np.ndarray], config: SiftConfig
                    ) -> list[tuple[int, int]]:
    """All pairs up to `exhaustive_up_to` images; beyond, retrieval neighbours plus sequence neighbours.
    The frames of a video (`pair_selection` video): `video_pairs`."""
    if config.pair_selection == "video":
        return sorted(video_pairs(names, descriptors, config))
    if len(names) <= config.exhaustive_up_to:
        return exhaustive_pairs(len(names))
    vocabulary = train_vocabulary(descriptors, config.vocabulary_size)
    pairs = retrieval_pairs(np.stack([vlad(d, vocabulary) for d in descriptors]), config.retrieval_neighbours)
    order = sequence_order(names)
    if order is not None and config.sequential_neighbours:
        pairs |= sequential_pairs(order, config.sequential_neighbours)
    return sorted(pairs)
