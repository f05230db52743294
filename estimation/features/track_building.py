"""Multi-view tracks from linked observations (match-file rows or pairwise SIFT matches).

Observations are nodes; a link says two nodes are the same physical point. A union-find joins
linked nodes into tracks, taking the links in the caller's order of trust, and refuses a link that
would put two different observations of one image into the same track (a wrong match chaining two
physical points): a track appears at most once per image. Tracks with fewer than two observations
are dropped.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from estimation.types import Tracks


class TrackAssembly(NamedTuple):
    """Tracks built from nodes, and which track each node landed in."""

    tracks: Tracks
    node_track: np.ndarray          # (N,) int: track of each node, -1 where dropped
    num_rejected_links: int         # links refused because they would see an image twice in a track
    observation_node: np.ndarray    # (O,) int: the node of each observation of `tracks`


class ImageAwareUnionFind:
    """Union-find over observation nodes that keeps, per set, the images its nodes lie in."""

    def __init__(self, node_image: np.ndarray) -> None:
        self.parent = list(range(len(node_image)))
        self.size = [1] * len(node_image)
        self.images = [1 << int(image) for image in node_image]     # bitmask of images per root

    def find(self, node: int) -> int:
        parent = self.parent
        while parent[node] != node:
            parent[node] = parent[parent[node]]     # path halving
            node = parent[node]
        return node

    def union(self, a: int, b: int) -> bool:
        """Join the sets of a and b unless they share an image; True if they are (now) one set."""
        root_a, root_b = self.find(a), self.find(b)
        if root_a == root_b:
            return True
        if self.images[root_a] & self.images[root_b]:
            return False
        if self.size[root_a] < self.size[root_b]:
            root_a, root_b = root_b, root_a
        self.parent[root_b] = root_a
        self.size[root_a] += self.size[root_b]
        self.images[root_a] |= self.images[root_b]
        return True

    def labels(self) -> np.ndarray:
        """The root of every node, by pointer jumping on the whole parent array (parent = parent[parent]
        until nothing moves) instead of a find per node."""
        parent = np.array(self.parent, np.int64)
        while True:
            grandparent = parent[parent]
            if np.array_equal(grandparent, parent):
                return parent
            parent = grandparent


def assemble_tracks(
    image_names: list[str],
    node_image: np.ndarray,
    node_uv: np.ndarray,
    node_color: np.ndarray,
    links: np.ndarray,
) -> TrackAssembly:
    """Tracks = union-find sets of the nodes under `links` (most trusted first), without image repeats.

    node_image (N,) image index, node_uv (N, 2) pixels, node_color (N, 3) RGB, links (E, 2) node ids.
    A track's colour is the mean colour of its nodes; tracks are numbered by their first node.
    """
    node_image = np.asarray(node_image, np.int64)
    num_nodes = node_image.size
    union_find = ImageAwareUnionFind(node_image)
    # Python ints (tolist): iterating numpy rows and converting their scalars cost 2-3 times the unions.
    rejected = sum(not union_find.union(a, b) for a, b in np.asarray(links, np.int64).reshape(-1, 2).tolist())
    labels = union_find.labels()

    kept_per_label = np.bincount(labels, minlength=num_nodes)
    keep = kept_per_label[labels] >= 2
    kept_nodes = np.flatnonzero(keep)
    kept_labels = labels[kept_nodes]
    # Number tracks in the order of their first node, so the output is deterministic.
    first_node_of_label = np.full(num_nodes, num_nodes, np.int64)
    np.minimum.at(first_node_of_label, kept_labels, kept_nodes)
    used_labels = np.unique(kept_labels)
    order = np.argsort(first_node_of_label[used_labels], kind="stable")
    label_to_track = np.full(num_nodes, -1, np.int64)
    label_to_track[used_labels[order]] = np.arange(used_labels.size)

    node_track = np.full(num_nodes, -1, np.int64)
    node_track[kept_nodes] = label_to_track[kept_labels]

    num_tracks = used_labels.size
    observation_nodes = kept_nodes[np.lexsort((node_image[kept_nodes], node_track[kept_nodes]))]
    color_sum = np.zeros((num_tracks, 3))
    np.add.at(color_sum, node_track[kept_nodes], np.asarray(node_color, float).reshape(-1, 3)[kept_nodes])
    color_count = np.bincount(node_track[kept_nodes], minlength=num_tracks)[:, None]
    colors = np.rint(color_sum / np.maximum(color_count, 1)).clip(0, 255).astype(np.uint8)

    tracks = Tracks(
        image_names=list(image_names),
        track_index=node_track[observation_nodes],
        image_index=node_image[observation_nodes],
        uv=np.asarray(node_uv, float).reshape(-1, 2)[observation_nodes],
        colors=colors,
    )
    return TrackAssembly(tracks=tracks, node_track=node_track, num_rejected_links=int(rejected),
                         observation_node=observation_nodes)
