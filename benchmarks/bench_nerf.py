"""NeRF benchmark: PSNR / SSIM on lego_200's val split against wall-clock training time, per model/resolution.

For every (model, resolution) a fresh run is trained with the product's trainer (`neural.train`, default
settings unless --model-option is given) for the first time budget, evaluated on the val split
(`neural.evaluate`, not counted as training time), then resumed (`train(..., resume=True)`) up to the next
budget, and so on: one training run gives the figures at 1, 2, 5 and 10 minutes. Then one 200x200 frame is
rendered and timed. Each (model, resolution) runs in its own subprocess so its peak memory (ru_maxrss) is
its own. Data: 100x100 -> ../shared/data/lego_tiny.npz (the same views, downscaled), 200x200 ->
../shared/data/lego_200. Prints a table and writes results.json into --out.

    python benchmarks/bench_nerf.py --models fast --resolutions 100 --minutes 1 2
    python benchmarks/bench_nerf.py  # everything: fast and vanilla, 100 and 200, 1-10 min

This is a benchmark, not a test: the full run takes about an hour on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
DATASETS = {100: DATA / "lego_tiny.npz", 200: DATA / "lego_200"}
TARGETS_DB = {("fast", 100): (2.0, 30.0), ("fast", 200): (5.0, 30.0)}  # the (minutes, dB) targets


def load_average() -> str:
    return " ".join(f"{value:.2f}" for value in os.getloadavg())


def run_one(
    model: str,
    resolution: int,
    minutes: list[float],
    out: Path,
    options: dict,
    train_options: dict,
    device: str,
) -> dict:
    """Train/evaluate one model at one resolution (called in the subprocess); returns its results."""
    import numpy as np
    import torch

    from neural import TrainConfig, evaluate, load_dataset, load_run, train
    from neural.inference import render_frame, view_camera

    data = DATASETS[resolution]
    run_dir = out / f"{model}_{resolution}"
    dataset = load_dataset(data)
    rows = []
    for index, budget in enumerate(sorted(minutes)):
        load_before = load_average()
        config = TrainConfig(
            model=model,
            model_options=options,
            minutes=budget,
            device=device,
            val_every=10**9,  # validation renders would count as training time
            checkpoint_every=10**9,
            log_every=50,
            **train_options,
        )
        result = train(data, run_dir, config if index == 0 else TrainConfig(minutes=budget), resume=index > 0)
        renders = run_dir / f"val_renders_{budget:g}min"  # PNGs to look at
        metrics = evaluate(run_dir, dataset, split="val", out_dir=renders)
        rows.append(
            {
                "minutes": budget,
                "train_seconds": result.seconds,
                "steps": result.step,
                "psnr": metrics.mean_psnr,
                "ssim": metrics.mean_ssim,
                "eval_seconds_per_image": metrics.seconds_per_image,
                "load_average_before": load_before,
                "load_average_after": load_average(),
            }
        )
        print(json.dumps({"model": model, "resolution": resolution, **rows[-1]}), file=sys.stderr, flush=True)

    run = load_run(run_dir, device=device)
    pose = dataset.normalization.pose_to_original(dataset.poses[dataset.split("val")[0]])
    camera = view_camera(run, 200, 200, None, None)
    render_frame(run, pose, camera)  # warm-up (allocations, lazy caches)
    start = time.perf_counter()
    render_frame(run, pose, camera)
    if run.device.type == "cuda":
        torch.cuda.synchronize()
    render_seconds = time.perf_counter() - start
    peak_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    peak_cuda_mib = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None
    return {
        "model": model,
        "resolution": resolution,
        "device": str(run.device),
        "threads": torch.get_num_threads(),
        "rows": rows,
        "render_200_seconds": render_seconds,
        "peak_rss_mib": peak_rss_mib,
        "peak_cuda_mib": peak_cuda_mib,
        "options": options,
        "train_options": train_options,
        "num_val_images": int(np.asarray(dataset.split("val")).size),
    }


def print_table(results: list[dict]) -> None:
    header = (
        f"{'model':8} {'res':>4} {'min':>5} {'train s':>8} {'steps':>6} {'PSNR':>6} {'SSIM':>6} "
        f"{'load avg (1/5/15 min)':>22}"
    )
    print(header)
    print("-" * len(header))
    for result in results:
        for row in result["rows"]:
            print(
                f"{result['model']:8} {result['resolution']:>4} {row['minutes']:>5g} "
                f"{row['train_seconds']:>8.1f} {row['steps']:>6} {row['psnr']:>6.2f} {row['ssim']:>6.3f} "
                f"{row['load_average_after']:>22}"
            )
    print()
    for result in results:
        line = (
            f"{result['model']} trained at {result['resolution']}x{result['resolution']} on "
            f"{result['device']} ({result['threads']} threads): one 200x200 frame renders in "
            f"{result['render_200_seconds']:.2f} s; "
            f"peak RSS {result['peak_rss_mib']:.0f} MiB"
        )
        if result["peak_cuda_mib"] is not None:
            line += f", peak CUDA {result['peak_cuda_mib']:.0f} MiB"
        print(line)
        target = TARGETS_DB.get((result["model"], result["resolution"]))
        if target is not None:
            within = [row for row in result["rows"] if row["minutes"] <= target[0]]
            if within:
                best = max(row["psnr"] for row in within)
                verdict = "met" if best >= target[1] else "NOT met"
                print(f"  target >= {target[1]} dB within {target[0]:g} min: {verdict} ({best:.2f} dB)")


def parse_options(pairs: list[str]) -> dict:
    options = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        if not key or not value:
            raise SystemExit(f"--model-option expects KEY=VALUE (JSON value), got {pair!r}")
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    return options


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--models", nargs="+", default=["fast", "vanilla"], choices=["fast", "vanilla"])
    parser.add_argument("--resolutions", nargs="+", type=int, default=[100, 200], choices=sorted(DATASETS))
    parser.add_argument("--minutes", nargs="+", type=float, default=[1, 2, 5, 10])
    parser.add_argument(
        "--threads", type=int, default=2, help="torch.set_num_threads (the machine has 2 cores)"
    )
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument(
        "--out", type=Path, default=Path("bench_nerf_runs"), help="run folders and results.json"
    )
    parser.add_argument(
        "--model-option", action="append", default=[], metavar="KEY=VALUE", help="model config override"
    )
    parser.add_argument(
        "--train-option", action="append", default=[], metavar="KEY=VALUE", help="TrainConfig override"
    )
    parser.add_argument("--single", nargs=2, metavar=("MODEL", "RES"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    options = parse_options(args.model_option)
    train_options = parse_options(args.train_option)

    if args.single:  # the subprocess for one (model, resolution)
        import torch

        torch.set_num_threads(args.threads)
        result = run_one(
            args.single[0], int(args.single[1]), args.minutes, args.out, options, train_options, args.device
        )
        (args.out / f"result_{args.single[0]}_{args.single[1]}.json").write_text(json.dumps(result, indent=2))
        return

    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for model in args.models:
        for resolution in args.resolutions:
            run_dir = args.out / f"{model}_{resolution}"
            if run_dir.exists():
                raise SystemExit(f"{run_dir} exists: choose another --out or remove it")
            command = [
                sys.executable, __file__, "--single", model, str(resolution), "--out", str(args.out),
                "--threads", str(args.threads), "--device", args.device, "--minutes",
                *[str(m) for m in args.minutes],
            ]  # fmt: skip
            for pair in args.model_option:
                command += ["--model-option", pair]
            for pair in args.train_option:
                command += ["--train-option", pair]
            print(f"== {model} at {resolution}x{resolution} (load average {load_average()})", flush=True)
            subprocess.run(command, check=True, cwd=REPO)
            results.append(json.loads((args.out / f"result_{model}_{resolution}.json").read_text()))
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print()
    print_table(results)


if __name__ == "__main__":
    main()
