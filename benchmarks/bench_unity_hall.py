"""Unity Hall end to end through `estimation.reconstruct`: seconds per stage and in total; prints a table.

Each run reconstructs ../shared/data/unity_hall into a fresh temporary folder. Stage seconds are the
ones the reconstruction reports (report.json's seconds_per_stage: input, features, the pipeline's
own stages, export, figures); "total (wall)" is the wall-clock time of the whole `reconstruct` call,
measured here. With --repeat N the table shows the median and the minimum over N runs (the machine is
shared: the minimum is the least disturbed run).

    python benchmarks/bench_unity_hall.py                       # match files, 3 runs
    python benchmarks/bench_unity_hall.py --features sift --repeat 1
    python benchmarks/bench_unity_hall.py --no-figures
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from estimation import ReconstructionConfig, reconstruct

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "unity_hall"


def run_once(data: Path, config: ReconstructionConfig) -> tuple[dict[str, float], float, dict]:
    """(seconds per stage, wall seconds, report) of one reconstruction into a temporary folder."""
    with tempfile.TemporaryDirectory(prefix="bench_unity_hall_") as out_dir:
        start = time.perf_counter()
        result = reconstruct(data, Path(out_dir), config)
        wall = time.perf_counter() - start
    return dict(result.report["seconds_per_stage"]), wall, result.report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="images folder (default: Unity Hall)")
    parser.add_argument("--features", choices=["auto", "matches", "sift"], default="auto")
    parser.add_argument("--repeat", type=int, default=3, help="runs; the table shows median and minimum")
    parser.add_argument("--no-figures", action="store_true", help="skip writing the PNG figures")
    args = parser.parse_args()

    config = ReconstructionConfig(features=args.features, write_figures=not args.no_figures)
    runs = [run_once(args.data, config) for _ in range(args.repeat)]
    stages = list(dict.fromkeys(name for seconds, _, _ in runs for name in seconds))
    rows = [(name, [seconds.get(name, 0.0) for seconds, _, _ in runs]) for name in stages]
    rows.append(("sum of stages", [sum(seconds.values()) for seconds, _, _ in runs]))
    rows.append(("total (wall)", [wall for _, wall, _ in runs]))

    report = runs[-1][2]
    after = report["reprojection_error_px"]["after_ba"]
    print(f"Unity Hall ({args.data}), features={report['features']['source']}, "
          f"figures={'no' if args.no_figures else 'yes'}, {args.repeat} run(s)")
    print(f"registered {report['images_registered']}/{report['images_total']} images, {report['points']} "
          f"points, RMS after BA {after['rms']:.3f} px (last run)\n")
    width = max(len(name) for name, _ in rows)
    print(f"| {'stage':<{width}} | median s | min s  | share |")
    print(f"|{'-' * (width + 2)}|----------|--------|-------|")
    total = statistics.median(rows[-1][1])
    for name, values in rows:
        median = statistics.median(values)
        print(f"| {name:<{width}} | {median:8.3f} | {min(values):6.3f} | {100 * median / total:4.0f}% |")


if __name__ == "__main__":
    main()
