"""Look-alike pairs: a verified pair of views from different sides whose relative rotation contradicts the
rotations that each image's strongest pairs agree on is left out; when those strongest pairs contradict each
other, none is, and the look-alikes of the rotations that keep the contradicted pairs, and of those that
contradict them, are the alternatives."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation.config import TwoViewConfig
from estimation.features.view_graph import (
    PairRotations,
    adopted_pairs,
    is_adopted,
    look_alike_pairs,
    registered_pairs,
    strongest_pairs,
)

HALF_TURN = Rotation.from_rotvec([0.0, np.pi, 0.0]).as_matrix()


def ring_rotations(num_images: int) -> np.ndarray:
    """World-to-camera rotations of cameras on a ring looking in: a turn about the vertical (y) each, tilted
    20 deg down."""
    azimuth = 2 * np.pi * np.arange(num_images) / num_images
    return (Rotation.from_rotvec([0.35, 0.0, 0.0]) * Rotation.from_rotvec(np.outer(azimuth, [0, 1, 0]))
            ).as_matrix()


def ring_with_look_alikes(num_images: int, neighbour_inliers: float, look_alike_inliers: float,
                          noise_deg: float = 2.0, seed: int = 0) -> tuple[PairRotations, set]:
    """A ring (pairs i, i+1 and i, i+2) whose images half a ring apart also verify, a half turn off: the
    far side of a symmetric object taken for its near side."""
    rng = np.random.default_rng(seed)
    world = ring_rotations(num_images)
    ring = [(i, (i + step) % num_images) for i in range(num_images) for step in (1, 2)]
    look_alikes = [(i, i + num_images // 2) for i in range(num_images // 2)]
    pairs = np.array([tuple(sorted(pair)) for pair in ring + look_alikes])
    noise = Rotation.from_rotvec(rng.normal(size=(len(pairs), 3)) * np.radians(noise_deg) / np.sqrt(3))
    R_relative = noise.as_matrix() @ world[pairs[:, 1]] @ world[pairs[:, 0]].swapaxes(1, 2)
    R_relative[len(ring):] = HALF_TURN @ R_relative[len(ring):]
    inliers = np.r_[np.full(len(ring), neighbour_inliers), np.full(len(look_alikes), look_alike_inliers)]
    inliers[:len(ring)] += rng.integers(0, 10, len(ring))
    return PairRotations(pairs, R_relative, inliers), set(look_alikes)


def test_each_images_strongest_pairs_are_its_per_image_pairs_with_the_most_inliers():
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (2, 3)])
    inliers = np.array([50.0, 40.0, 10.0, 20.0, 30.0])
    # 0: (0,1), (0,2); 1: (0,1), (1,2); 2: (0,2), (2,3); 3: (2,3), (0,3)
    assert strongest_pairs(pairs, inliers, 2).tolist() == [True, True, True, True, True]
    # 0: (0,1); 1: (0,1); 2: (0,2); 3: (2,3)
    assert strongest_pairs(pairs, inliers, 1).tolist() == [True, True, False, False, True]


def test_the_half_turned_look_alikes_of_a_ring_are_left_out_and_its_neighbours_kept():
    rotations, look_alikes = ring_with_look_alikes(24, neighbour_inliers=100, look_alike_inliers=60)
    found = look_alike_pairs(24, rotations, TwoViewConfig())
    assert set(found.pairs) == look_alikes and not found.conflicts
    assert found.residual_deg[:48].max() < 10.0


def test_a_pair_of_neighbours_whose_e_is_far_off_is_kept_its_matches_agree():
    # The E of a small object seen from afar may trade rotation for translation by tens of degrees.
    rotations, look_alikes = ring_with_look_alikes(24, neighbour_inliers=100, look_alike_inliers=60)
    R_relative = rotations.R_relative.copy()
    k = rotations.pairs.tolist().index([3, 5])
    R_relative[k] = Rotation.from_rotvec([0.0, 0.0, 2.2]).as_matrix() @ R_relative[k]
    found = look_alike_pairs(24, rotations._replace(R_relative=R_relative), TwoViewConfig())
    assert found.residual_deg[k] > 120.0
    assert set(found.pairs) == look_alikes


def test_look_alikes_stronger_than_the_rings_weakest_links_are_still_found():
    # A spanning tree of the most inliers alone would take a look-alike instead of the two weak links.
    rotations, look_alikes = ring_with_look_alikes(24, neighbour_inliers=100, look_alike_inliers=60)
    inliers = rotations.inliers.copy()
    weak = [k for k, pair in enumerate(rotations.pairs.tolist()) if tuple(pair) in {(5, 6), (17, 18)}]
    inliers[weak] = 30.0
    found = look_alike_pairs(24, rotations._replace(inliers=inliers), TwoViewConfig())
    assert set(found.pairs) == look_alikes


def test_a_look_alike_among_an_images_strongest_pairs_leaves_every_pair_in_and_names_a_conflict():
    rotations, _ = ring_with_look_alikes(16, neighbour_inliers=30, look_alike_inliers=20)
    inliers = rotations.inliers.copy()
    inliers[rotations.pairs.tolist().index([2, 10])] = 200.0     # image 2's and 10's strongest pair
    found = look_alike_pairs(16, rotations._replace(inliers=inliers), TwoViewConfig())
    # Either the look-alike or the ring's links it contradicts: which one cannot be told.
    assert found.pairs == [] and found.conflicts


def sparse_ring(num_images: int, link_inliers: dict, look_alike_inliers: dict, seed: int = 0
                ) -> tuple[PairRotations, set]:
    """A ring of neighbour pairs (i, i+1) only, 100 inliers each but for `link_inliers`, whose views half a
    ring apart also verify, a half turn off, 40 inliers each but for `look_alike_inliers`: a sparse capture
    of a symmetric object."""
    rng = np.random.default_rng(seed)
    world = ring_rotations(num_images)
    ring = [tuple(sorted((i, (i + 1) % num_images))) for i in range(num_images)]
    look_alikes = [(i, i + num_images // 2) for i in range(num_images // 2)]
    pairs = np.array(ring + look_alikes)
    noise = Rotation.from_rotvec(rng.normal(size=(len(pairs), 3)) * np.radians(2.0) / np.sqrt(3))
    R_relative = noise.as_matrix() @ world[pairs[:, 1]] @ world[pairs[:, 0]].swapaxes(1, 2)
    R_relative[len(ring):] = HALF_TURN @ R_relative[len(ring):]
    inliers = np.array([link_inliers.get(pair, 100.0) for pair in ring]
                       + [look_alike_inliers.get(pair, 40.0) for pair in look_alikes])
    return PairRotations(pairs, R_relative, inliers), set(look_alikes)


def test_where_a_look_alike_beats_the_link_that_closes_a_sparse_ring_the_first_alternative_keeps_that_link():
    # Image 3's second strongest pair is its look-alike (3, 13): the tree of the strongest pairs takes it
    # before the weaker links (2, 3) and (7, 8), which the averaged rotations then contradict.
    rotations, look_alikes = sparse_ring(20, {(2, 3): 70.0, (7, 8): 80.0, (17, 18): 80.0}, {(3, 13): 90.0})
    found = look_alike_pairs(20, rotations, TwoViewConfig())
    assert found.pairs == [] and set(found.conflicts) == {(2, 3), (7, 8)}
    # The rotations that keep the contradicted links put every look-alike half a turn off.
    assert set(found.alternatives[0]) == look_alikes
    # Those averaged over every strongest pair put the contradicted links on other sides, and keep the
    # look-alike that took their place.
    assert set(found.conflicts) <= set(found.alternatives[1]) and (3, 13) not in found.alternatives[1]


def test_without_conflicts_there_are_no_alternatives():
    rotations, look_alikes = sparse_ring(20, {}, {})
    found = look_alike_pairs(20, rotations, TwoViewConfig())
    assert set(found.pairs) == look_alikes and found.conflicts == [] and found.alternatives == ()


@pytest.mark.parametrize("config", [TwoViewConfig(max_rotation_residual_deg=None), TwoViewConfig()])
def test_without_the_limit_or_without_look_alikes_every_pair_is_kept(config):
    rotations, _ = ring_with_look_alikes(12, neighbour_inliers=100, look_alike_inliers=60)
    ring_only = PairRotations(*(array[:24] for array in rotations))
    assert look_alike_pairs(12, rotations if config.max_rotation_residual_deg is None else ring_only,
                            config).pairs == []


def test_a_model_that_placed_its_far_side_as_the_look_alikes_say_has_adopted_them_and_one_in_place_none():
    rotations, look_alikes = ring_with_look_alikes(24, neighbour_inliers=100, look_alike_inliers=60)
    in_place = ring_rotations(24)
    assert adopted_pairs(rotations, sorted(look_alikes), in_place) == []
    folded = in_place.copy()
    for (i, j), R_ij in zip(rotations.pairs.tolist(), rotations.R_relative, strict=True):
        if (i, j) in look_alikes:
            folded[j] = R_ij @ in_place[i]          # the far side's camera j put where the look-alike says
    assert set(adopted_pairs(rotations, sorted(look_alikes), folded)) == look_alikes
    folded[0] = np.nan                              # image 0 not registered: its pair is not judged
    assert set(adopted_pairs(rotations, sorted(look_alikes), folded)) == look_alikes - {(0, 12)}


def test_a_model_is_folded_when_it_adopted_a_few_look_alikes_and_most_of_those_between_its_images():
    rotations, look_alikes = ring_with_look_alikes(24, neighbour_inliers=100, look_alike_inliers=60)
    pairs = sorted(look_alikes)                      # (i, i + 12)
    in_place = ring_rotations(24)
    folded = in_place.copy()
    for (i, j), R_ij in zip(rotations.pairs.tolist(), rotations.R_relative, strict=True):
        if (i, j) in look_alikes and i < 4:
            folded[j] = R_ij @ in_place[i]          # 4 of the 12 adopted, all 12 between registered images
    assert registered_pairs(pairs, folded) == pairs and len(adopted_pairs(rotations, pairs, folded)) == 4
    assert not is_adopted(rotations, pairs, folded, min_adopted=3)          # 4 of 12: not most
    partial = folded.copy()
    partial[[16, 17, 18, 19, 20, 21, 22, 23]] = np.nan                  # 4 of the 4 between registered ones
    assert registered_pairs(pairs, partial) == pairs[:4]
    assert is_adopted(rotations, pairs, partial, min_adopted=3)
    assert not is_adopted(rotations, pairs, partial, min_adopted=5)     # too few, however large the share
