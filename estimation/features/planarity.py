"""The verified pairs' planarity tests (`two_view.geometry.classify_planarity`: H in RANSAC), run by the front
end's worker process while the mapper works.

The test can only relabel a pair planar or panoramic (so that it does not start a model); it never changes
a pair's inliers, so the tracks are made without it. In the front end, where both cores are busy, it took
~0.35 of lego's ~6 CPU s; the mapper that follows runs on one core, and the front end's worker process is
still there, its modules imported. The mapper looks up only its initial-pair candidates' types (29 on lego,
the pairs sharing most tracks): the worker tests the pairs with most inliers first, in small chunks, so that
those lookups find their tests done; one looked up before its chunk is done is tested in this process (the
same result: each test's RANSAC is seeded). `geometries()` waits for the rest (the report lists every pair).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from contextlib import suppress

import numpy as np

from estimation.config import RansacConfig, TwoViewConfig
from estimation.parallel import WorkerPool
from estimation.two_view.geometry import TwoViewGeometry, classify_planarity

Pair = tuple[int, int]
PAIRS_PER_CHUNK = 16
"""Pairs per planarity task (~1 ms each on lego): the first chunks are back before most of the mapper's
lookups, which repeated all 29 of their tests (30 ms) in this process while the worker tested the pairs in
image order (now 8-12 of them: `python -m cProfile benchmarks/bench_sfm.py --sets lego --no-pycolmap`)."""


def classify_pairs(geometries: list[TwoViewGeometry], uv: list[tuple[np.ndarray, np.ndarray]],
                   K: np.ndarray | None, config: TwoViewConfig, ransac: RansacConfig
                   ) -> list[TwoViewGeometry]:
    """`classify_planarity` of each pair (its geometry and the pixels of its matches in both images)."""
    return [classify_planarity(geometry, uv1, uv2, K, K, config, ransac)
            for geometry, (uv1, uv2) in zip(geometries, uv, strict=True)]


class PairTypes(Mapping[Pair, str]):
    """Each verified pair's two-view type by (i, j), i < j. The pairs whose planarity is untested are tested
    in `pool` (handed over: `close` shuts it down) beside the caller's work, or in this process at a lookup
    that comes first; `geometries()` gives them all."""

    def __init__(self, geometries: dict[Pair, TwoViewGeometry],
                 untested_uv: dict[Pair, tuple[np.ndarray, np.ndarray]], K: np.ndarray | None,
                 config: TwoViewConfig, ransac: RansacConfig, pool: WorkerPool) -> None:
        self._geometries = {(min(pair), max(pair)): geometry for pair, geometry in geometries.items()}
        self._uv = {(min(pair), max(pair)): uv for pair, uv in untested_uv.items()}
        self._settings = (K, config, ransac)
        untested = [pair for pair, geometry in self._geometries.items() if not geometry.planarity_tested]
        untested.sort(key=lambda pair: -self._geometries[pair].num_inliers)
        self._pool: WorkerPool | None = pool
        self._chunks: list[tuple[list[Pair], Future]] = []   # the worker's tasks, strongest pairs first
        self._chunk_of: dict[Pair, int] = {}
        with suppress(BrokenProcessPool):     # a dead worker: the pairs are tested in this process
            for start in range(0, len(untested), PAIRS_PER_CHUNK):
                chunk = untested[start:start + PAIRS_PER_CHUNK]
                future = pool.submit(classify_pairs, [self._geometries[pair] for pair in chunk],
                                     [self._uv[pair] for pair in chunk], *self._settings)
                self._chunk_of.update(dict.fromkeys(chunk, len(self._chunks)))
                self._chunks.append((chunk, future))

    def _collect(self, chunk: int) -> None:
        """The worker's results for one chunk (waited for), unless its process died."""
        pairs, future = self._chunks[chunk]
        with suppress(BrokenProcessPool):     # a dead worker: they are tested in this process when looked up
            self._geometries.update(zip(pairs, future.result(), strict=True))

    def _tested(self, pair: Pair) -> TwoViewGeometry:
        geometry = self._geometries[pair]
        if not geometry.planarity_tested:
            chunk = self._chunk_of.get(pair)
            if chunk is not None and self._chunks[chunk][1].done():
                self._collect(chunk)
                geometry = self._geometries[pair]
        if not geometry.planarity_tested:
            geometry = classify_pairs([geometry], [self._uv[pair]], *self._settings)[0]
            self._geometries[pair] = geometry
        return geometry

    def __getitem__(self, pair: Pair) -> str:
        return self._tested(pair).type.value

    def __iter__(self) -> Iterator[Pair]:
        return iter(self._geometries)

    def __len__(self) -> int:
        return len(self._geometries)

    def epipolar_geometries(self) -> dict[Pair, TwoViewGeometry]:
        """Every pair's geometry as verified, without waiting for the planarity tests (which change only
        the type: E, F and the inliers are final)."""
        return dict(self._geometries)

    def geometries(self) -> dict[Pair, TwoViewGeometry]:
        """Every pair's geometry, its planarity tested: the worker's results (waited for; tested here instead
        if its process died); the pool is shut down."""
        for chunk in range(len(self._chunks)):
            self._collect(chunk)
        self._chunks, self._chunk_of = [], {}
        # Its results in, the worker process exits beside the caller's next work (its exit took ~0.05 s).
        self.close(wait=False)
        return {pair: self._tested(pair) for pair in self._geometries}

    def close(self, wait: bool = True) -> None:
        """Shuts the pool down (after the test it is running, if any); `wait`: until its process exited."""
        if self._pool is not None:
            self._pool.shutdown(wait)
            self._pool = None
