"""The planarity tests run beside the caller: every pair gets the type the whole verification gives it, in
the worker process or, when looked up first or when that process died, in the calling one."""

import os
import signal
import time
from concurrent.futures import Future

import numpy as np
import pytest

from estimation.config import RansacConfig, TwoViewConfig
from estimation.features import planarity
from estimation.features.planarity import PairTypes
from estimation.parallel import WorkerPool
from estimation.synthetic import project, rotation_about_axis
from estimation.two_view.geometry import estimate_two_view_geometry, verify_epipolar
from estimation.types import CameraPose

MODULES = ("estimation.features.planarity",)
K = np.array([[600.0, 0.0, 400.0], [0.0, 600.0, 300.0], [0.0, 0.0, 1.0]])
CONFIG, RANSAC = TwoViewConfig(), RansacConfig()


def correspondences(seed: int, planar: bool, baseline: float) -> tuple[np.ndarray, np.ndarray]:
    """A plane or a general scene seen from the origin and from a camera turned by 8 deg, `baseline` away."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(4.0, 8.0, 200)
    points = np.stack([rng.uniform(-0.5, 0.5, 200) * z, rng.uniform(-0.4, 0.4, 200) * z, z], axis=1)
    if planar:
        points[:, 2] = 6.0 + 0.3 * points[:, 0]
    turned = rotation_about_axis([0, 1, 0], np.deg2rad(-8))
    second = CameraPose.from_center(turned, np.array([baseline, 0, 0]))
    uv1 = project(K, CameraPose(np.eye(3), np.zeros(3)), points) + rng.normal(0, 0.5, (200, 2))
    return uv1, project(K, second, points) + rng.normal(0, 0.5, (200, 2))


@pytest.fixture(scope="module")
def pairs():
    """(i, j) -> pixels of a general pair, a plane, and a pure rotation."""
    return {(0, 1): correspondences(1, planar=False, baseline=1.0),
            (1, 2): correspondences(2, planar=True, baseline=1.0),
            (0, 2): correspondences(3, planar=False, baseline=0.0)}


def pair_types(pairs, pool: WorkerPool) -> PairTypes:
    untested = {pair: verify_epipolar(*uv, K, K, CONFIG, RANSAC) for pair, uv in pairs.items()}
    return PairTypes(untested, pairs, K, CONFIG, RANSAC, pool)


def expected(pairs) -> dict:
    return {pair: estimate_two_view_geometry(*uv, K, K, CONFIG, RANSAC) for pair, uv in pairs.items()}


@pytest.mark.parametrize("workers", [1, 2])
def test_every_pair_gets_the_type_and_h_of_the_whole_verification(pairs, workers):
    types = pair_types(pairs, WorkerPool(workers, modules=MODULES, caller_works=True))
    whole = expected(pairs)
    assert {pair: types[pair] for pair in pairs} == {pair: g.type.value for pair, g in whole.items()}
    assert {g.type.value for g in whole.values()} == {"calibrated", "planar", "panoramic"}
    for pair, geometry in types.geometries().items():
        assert geometry.planarity_tested and geometry.type == whole[pair].type
        np.testing.assert_array_equal(geometry.H, whole[pair].H)
        np.testing.assert_array_equal(geometry.inlier_mask, whole[pair].inlier_mask)


def test_a_pair_looked_up_is_keyed_by_its_smaller_image_first(pairs):
    types = pair_types({(2, 1): pairs[(1, 2)]}, WorkerPool(1))
    assert types.get((1, 2)) == "planar" and types.get((2, 1)) is None


def test_the_pairs_are_tested_here_when_the_worker_process_died(pairs):
    pool = WorkerPool(2, modules=MODULES, caller_works=True)
    for pid in list(pool._executor._processes):     # the one worker process, dead before the tests are sent
        os.kill(pid, signal.SIGKILL)
    time.sleep(0.2)
    types = pair_types(pairs, pool)
    tested = {pair: geometry.type for pair, geometry in types.geometries().items()}
    assert tested == {pair: geometry.type for pair, geometry in expected(pairs).items()}


def test_the_worker_process_ends_once_the_results_are_in(pairs):
    pool = WorkerPool(2, modules=MODULES, caller_works=True)
    (process,) = pool._executor._processes.values()
    pair_types(pairs, pool).geometries()   # not waiting for the process to exit (the caller goes on)
    deadline = time.monotonic() + 30       # the pool's thread reaps it: join() here would race that thread
    while process.exitcode is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert process.exitcode == 0


class RecordingPool:
    """Runs each submitted task at once, recording the inlier counts of the pairs it was given."""

    def __init__(self) -> None:
        self.tasks: list[list[int]] = []

    def submit(self, function, geometries, *args):
        self.tasks.append([geometry.num_inliers for geometry in geometries])
        future = Future()
        future.set_result(function(geometries, *args))
        return future

    def shutdown(self, wait: bool = True) -> None:
        pass


def test_the_worker_tests_the_pairs_with_most_inliers_first_a_chunk_at_a_time(pairs, monkeypatch):
    monkeypatch.setattr(planarity, "PAIRS_PER_CHUNK", 2)
    # fewest inliers in the first pair of image order, most in the last
    sizes = dict(zip(pairs, (60, 200, 120), strict=True))
    sized = {pair: (uv1[:sizes[pair]], uv2[:sizes[pair]]) for pair, (uv1, uv2) in pairs.items()}
    pool = RecordingPool()
    types = pair_types(sized, pool)
    assert pool.tasks == [[200, 120], [60]]
    assert {pair: geometry.type for pair, geometry in types.geometries().items()} == {
        pair: geometry.type for pair, geometry in expected(sized).items()}
