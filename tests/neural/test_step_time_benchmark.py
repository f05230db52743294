"""bench_nerf_real.py --step-time: the interleaved timing and the ratios it prints."""

from __future__ import annotations

import pytest


@pytest.fixture
def bench(benchmark_module):
    return benchmark_module("bench_nerf_real")


def test_step_functions_are_called_in_turn_and_each_call_is_timed(bench, monkeypatch):
    # A clock that only the step functions advance, so that the test reads no real machine load.
    now = [0.0]
    monkeypatch.setattr(bench.time, "perf_counter", lambda: now[0])
    calls = []

    def step(name, seconds):
        def call():
            calls.append(name)
            now[0] += seconds

        return call

    seconds = bench.interleaved_step_seconds({"slow": step("slow", 0.02), "fast": step("fast", 0.001)}, 3)
    assert calls == ["slow", "fast"] * 3
    assert seconds["slow"] == pytest.approx([0.02] * 3)
    assert seconds["fast"] == pytest.approx([0.001] * 3)


def test_summary_gives_ratios_to_the_reference_per_step_and_per_ray(bench):
    seconds = {"lego": [0.1, 0.1, 0.1, 0.1], "photos": [0.4, 0.2, 0.2, 0.2]}
    summary = bench.step_time_summary(seconds, {"lego": 4096, "photos": 4608}, "lego")
    rows = {row["run"]: row for row in summary}
    assert rows["lego"]["ratio"] == pytest.approx(1.0)
    assert rows["photos"]["seconds_per_step"] == pytest.approx(0.25)
    assert rows["photos"]["last_quarter_seconds"] == pytest.approx(0.2)
    assert rows["photos"]["ratio"] == pytest.approx(2.5)
    assert rows["photos"]["ratio_per_ray"] == pytest.approx(2.5 * 4096 / 4608)
