"""Union-find track building: chains become tracks, and no track ever sees an image twice."""

from __future__ import annotations

import numpy as np

from estimation.features.track_building import ImageAwareUnionFind, assemble_tracks

NAMES = ["a.png", "b.png", "c.png", "d.png"]


def test_chained_pairwise_links_form_one_multiview_track():
    # Nodes: 0 in image 0, 1 in image 1, 2 in image 2, 3 in image 3; links 0-1, 1-2, 2-3.
    assembly = assemble_tracks(NAMES, np.array([0, 1, 2, 3]), np.arange(8.0).reshape(4, 2),
                               np.full((4, 3), 10), np.array([[0, 1], [1, 2], [2, 3]]))
    tracks = assembly.tracks
    assert tracks.num_tracks == 1
    np.testing.assert_array_equal(tracks.image_index, [0, 1, 2, 3])
    np.testing.assert_array_equal(tracks.uv, np.arange(8.0).reshape(4, 2))
    assert assembly.num_rejected_links == 0


def test_a_link_joining_two_observations_of_one_image_is_refused_first_links_win():
    # Nodes 0 and 3 both lie in image 0; the last link would join them through node 2.
    node_image = np.array([0, 1, 2, 0])
    links = np.array([[0, 1], [1, 2], [3, 2]])
    assembly = assemble_tracks(NAMES, node_image, np.zeros((4, 2)), np.zeros((4, 3)), links)
    assert assembly.num_rejected_links == 1
    np.testing.assert_array_equal(assembly.node_track, [0, 0, 0, -1])     # node 3 is left alone: dropped


def test_track_colour_is_the_mean_of_its_observations_and_singletons_are_dropped():
    colors = np.array([[0, 0, 0], [100, 50, 255], [7, 7, 7]])
    assembly = assemble_tracks(NAMES, np.array([0, 1, 2]), np.zeros((3, 2)), colors, np.array([[0, 1]]))
    np.testing.assert_array_equal(assembly.tracks.colors, [[50, 25, 128]])
    np.testing.assert_array_equal(assembly.node_track, [0, 0, -1])


def test_tracks_are_numbered_by_first_node_and_observations_sorted_by_track_then_image():
    node_image = np.array([2, 0, 1, 3])
    links = np.array([[2, 3], [0, 1]])                                   # tracks {0, 1} and {2, 3}
    tracks = assemble_tracks(NAMES, node_image, np.arange(8.0).reshape(4, 2), np.zeros((4, 3)), links).tracks
    np.testing.assert_array_equal(tracks.track_index, [0, 0, 1, 1])
    np.testing.assert_array_equal(tracks.image_index, [0, 2, 1, 3])
    np.testing.assert_array_equal(tracks.uv, [[2, 3], [0, 1], [4, 5], [6, 7]])


def test_no_links_give_no_tracks():
    no_links = np.zeros((0, 2), np.int64)
    tracks = assemble_tracks(NAMES, np.array([0, 1]), np.zeros((2, 2)), np.zeros((2, 3)), no_links).tracks
    assert tracks.num_tracks == 0 and tracks.uv.shape == (0, 2)


def test_union_find_labels_are_each_nodes_root():
    rng = np.random.default_rng(3)
    union_find = ImageAwareUnionFind(np.arange(500) % 40)
    for a, b in rng.integers(0, 500, (400, 2)).tolist():
        union_find.union(a, b)
    np.testing.assert_array_equal(union_find.labels(), [union_find.find(node) for node in range(500)])
