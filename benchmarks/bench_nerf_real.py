"""NeRF on real photographs: Strecha's fountain-P11 and Herz-Jesus-P8 through `sfmnerf reconstruct`, then the
fast model trained at <= --max-side px in two configurations, scored on held-out views only.

Configurations (both the fast model with its default settings otherwise):
- `unbounded`: what `sfmnerf nerf train` chooses for reconstructions: contracted unbounded scene, random
  background during training (renders on the photos' environment, neural.environment; the same field is
  also scored on black, the environment's ablation);
- `box`: the configuration before it: the sparse points' box with a white background.
Both train the depth loss on the reconstruction's depths.npz (the default for reconstructions); the ablation
of it is `--variant 'constant={"depth_uncertainty": "constant"}' --variant 'no-depth={"depth_supervision":
false}'`.

Each scene is reconstructed once with SIFT and its calibration.txt (`sfmnerf reconstruct`, full-size
images: the command has no image-size option), into OUT/sfm/SCENE (kept and reused on a second run). Each
(scene, configuration) trains in its own subprocess (so its peak RSS is its own) for --minutes of wall-clock
time, then is evaluated (`neural.evaluate`) on the held-out split (LLFF: every 8th image from the first;
never trained on): PSNR and SSIM at the training size. The held-out renders are written as
OUT/SCENE/CONFIG/heldout/NAME.png beside NAME_truth.png, and one 800x600 frame is rendered and timed.
Prints a table and writes OUT/results.json. With --side-by-side, a scene's configurations train at the same
time in their own processes (give each one thread: `--threads 1` on 2 cores), so they share the machine's
conditions (load from others included) and a scene takes --minutes of wall-clock.

    python benchmarks/bench_nerf_real.py --minutes 3 --out /tmp/bench_real
    python benchmarks/bench_nerf_real.py --side-by-side --threads 1 --out /tmp/r
    python benchmarks/bench_nerf_real.py --scenes fountain-P11 --configurations unbounded --steps 300 \
        --max-side 400 --threads 1 --variant 'tv={"model_options": {"tv_density_weight": 1e-4}}'

--step-time compares the cost of a training step instead: Lego (200 px, its defaults) and each scene in each
configuration train in one process, one step of each in turn, so every one meets the same load; it prints
their mean seconds per step (over all --steps, and over the last quarter, after the grids' last upsampling)
and the ratio to Lego's at the same colour rays per step (the photos add their depth rays).

    python benchmarks/bench_nerf_real.py --step-time --steps 600 --max-side 400 --threads 1 --out /tmp/st

The ablation of the occupancy rule for occluded cells (for --step-time, and for held-out PSNR at the same
wall-clock with --side-by-side): `--variant 'rendered-seen={"model_options": {"occupancy_seen_occluded":
false}}'`.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from bench_nerf import load_average, with_variants

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
#: The reference of --step-time, under --data-root: Lego's 200 px views (bench_nerf.py's), its defaults.
LEGO = "lego_200"
SCENES = ("fountain-P11", "Herz-Jesus-P8")
#: TrainConfig settings of each configuration (the rest: the fast model's defaults).
CONFIGURATIONS: dict[str, dict] = {
    "unbounded": {},  # the reconstruction's defaults: unbounded, random background
    "box": {"unbounded": False, "background": "white"},
}
RENDER_SIZE = (800, 600)
#: --step-time without --steps: past the fast model's last grid upsampling (step 400).
STEP_TIME_STEPS = 600
#: `sfmnerf` of this checkout (the installed script may import another one).
CLI = "import sys; from service.cli import main; sys.argv[0] = 'sfmnerf'; main()"


def reconstruct(scene: str, out: Path, data_root: Path) -> dict:
    """`sfmnerf reconstruct` of DATA_ROOT/strecha/SCENE into OUT/sfm/SCENE unless it is there; its report and
    seconds."""
    folder = out / "sfm" / scene
    seconds = None
    if not (folder / "transforms.json").is_file():
        start = time.perf_counter()
        command = [sys.executable, "-c", CLI, "reconstruct", str(data_root / "strecha" / scene),
                   "--out", str(folder), "--features", "sift"]  # fmt: skip
        subprocess.run(command, check=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
        seconds = time.perf_counter() - start
    report = json.loads((folder / "report.json").read_text())
    return {
        "scene": scene,
        "folder": str(folder),
        "seconds": seconds,
        "registered": f"{report['images_registered']}/{report['images_total']}",
        "points": report["points"],
    }


def run_one(
    scene: str, configuration: str, settings: dict, out: Path, budget: dict, max_side: int, device: str,
    frame: bool = True,
) -> dict:
    """Train, evaluate and time one (scene, configuration); called in the subprocess.

    settings: the configuration's TrainConfig fields; budget: {"minutes": M} or {"steps": N}.
    """
    import numpy as np
    import torch
    from PIL import Image

    from neural import TrainConfig, evaluate, load_run, train
    from neural.artefacts import IMAGE_CACHE_DIR
    from neural.data import load_dataset_for
    from neural.environment import Environment
    from neural.evaluation import evaluate_run
    from neural.inference import background_colour, render_frame, to_uint8, view_camera

    data = out / "sfm" / scene
    run_dir = out / scene / configuration
    load_before = load_average()
    config = TrainConfig(
        **{"model": "fast", **budget, **settings},
        max_side=max_side,
        device=device,
        val_every=10**9,  # validation renders would count as training time
        checkpoint_every=10**9,
        log_every=50,
    )
    result = train(data, run_dir, config)
    load_after = load_average()
    heldout = run_dir / "heldout"
    metrics = evaluate(run_dir, data, split="val", out_dir=heldout, device=device)
    run = load_run(run_dir, device=device)
    dataset = load_dataset_for(data, run.config, run_dir / IMAGE_CACHE_DIR)
    on_black = None  # the same field rendered without the photos' environment: its ablation, exact
    if isinstance(run.background, Environment):
        on_black = evaluate_run(replace(run, background=background_colour("black", run.device)), dataset)
    for index in dataset.split("val"):
        name = Path(dataset.image_names[index]).stem
        Image.fromarray(to_uint8(dataset.images[index])).save(heldout / f"{name}_truth.png")

    render_seconds = float("nan")
    if frame:
        pose = dataset.normalization.pose_to_original(dataset.poses[dataset.split("val")[0]])
        camera = view_camera(run, *RENDER_SIZE, None, None)
        with torch.no_grad():
            render_frame(run, pose, camera)  # warm-up
            start = time.perf_counter()
            rendered = render_frame(run, pose, camera)
            if run.device.type == "cuda":
                torch.cuda.synchronize()
            render_seconds = time.perf_counter() - start
        Image.fromarray(to_uint8(rendered.rgb)).save(run_dir / "render_800x600.png")
    stored = json.loads((run_dir / "config.json").read_text())
    return {
        "scene": scene,
        "configuration": configuration,
        "device": str(run.device),
        "threads": torch.get_num_threads(),
        "minutes": budget.get("minutes"),
        "train_seconds": result.seconds,
        "steps": result.step,
        "image_size": [dataset.width, dataset.height],
        "heldout_images": [m.name for m in metrics.per_image],
        "psnr": metrics.mean_psnr,
        "ssim": metrics.mean_ssim,
        "psnr_on_black": None if on_black is None else on_black.mean_psnr,
        "ssim_on_black": None if on_black is None else on_black.mean_ssim,
        "per_image": [{"name": m.name, "psnr": m.psnr, "ssim": m.ssim} for m in metrics.per_image],
        "render_800x600_seconds": render_seconds,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "peak_cuda_mib": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
        "train_config": stored["train"],
        "depth_supervision": stored.get("depth_supervision"),
        "scene_info": stored["scene"],
        "load_average_before": load_before,
        "load_average_after_training": load_after,
        "num_train_images": int(np.asarray(dataset.split("train")).size),
    }


def interleaved_step_seconds(step_fns: dict[str, Callable[[], object]], steps: int) -> dict[str, list[float]]:
    """Seconds of each of `steps` calls of every step function, the functions called in turn (one call of
    each, then the next round), so that all of them meet the same machine load."""
    seconds: dict[str, list[float]] = {name: [] for name in step_fns}
    for _ in range(steps):
        for name, step in step_fns.items():
            start = time.perf_counter()
            step()
            seconds[name].append(time.perf_counter() - start)
    return seconds


def step_time_summary(seconds: dict[str, list[float]], rays: dict[str, int], reference: str) -> list[dict]:
    """Per run: mean seconds per step over all steps and over the last quarter, rays per step, and both
    ratios to the reference's mean (per step, and per ray)."""
    rows = []
    for name, times in seconds.items():
        last = times[-max(1, len(times) // 4) :]
        rows.append({
            "run": name, "steps": len(times), "rays_per_step": rays[name],
            "seconds_per_step": sum(times) / len(times), "last_quarter_seconds": sum(last) / len(last),
        })  # fmt: skip
    base = next(row for row in rows if row["run"] == reference)
    for row in rows:
        row["ratio"] = row["seconds_per_step"] / base["seconds_per_step"]
        row["ratio_per_ray"] = row["ratio"] * base["rays_per_step"] / row["rays_per_step"]
    return rows


def step_time_comparison(
    scenes: list[str], configurations: dict[str, dict], out: Path, max_side: int, steps: int, device: str,
    lego: Path,
) -> list[dict]:
    """Lego and every (scene, configuration) trained `steps` steps in this process, steps interleaved."""
    from neural import TrainConfig
    from neural.training import Trainer

    logging = {"val_every": 10**9, "checkpoint_every": 10**9, "log_every": 10**9, "device": device}
    runs = {"lego": (lego, TrainConfig(model="fast", steps=steps, **logging))}
    for scene in scenes:
        for name, settings in configurations.items():
            config = TrainConfig(**{"model": "fast", **settings}, steps=steps, max_side=max_side, **logging)
            runs[f"{scene} {name}"] = (out / "sfm" / scene, config)
    trainers = {
        name: Trainer(data, out / "step_time" / name.replace(" ", "_"), config, False, None, None, None)
        for name, (data, config) in runs.items()
    }
    rays = {
        name: trainer.config.batch_rays + (trainer.config.depth_rays if trainer.depth_sampler else 0)
        for name, trainer in trainers.items()
    }
    seconds = interleaved_step_seconds({name: t.train_step for name, t in trainers.items()}, steps)
    return step_time_summary(seconds, rays, "lego")


def print_step_times(rows: list[dict]) -> None:
    header = (f"{'run':28} {'steps':>6} {'rays/step':>9} {'s/step':>8} {'last 1/4':>8} {'x lego':>7} "
              f"{'x lego per ray':>14}")  # fmt: skip
    print(header)
    print("-" * len(header))
    for row in rows:
        print(
            f"{row['run']:28} {row['steps']:>6} {row['rays_per_step']:>9} {row['seconds_per_step']:>8.3f} "
            f"{row['last_quarter_seconds']:>8.3f} {row['ratio']:>7.2f} {row['ratio_per_ray']:>14.2f}"
        )


def print_table(sfm: list[dict], results: list[dict]) -> None:
    for entry in sfm:
        took = "reused" if entry["seconds"] is None else f"{entry['seconds']:.0f} s"
        print(f"sfm {entry['scene']}: {entry['registered']} registered, {entry['points']} points ({took})")
    header = (
        f"{'scene':14} {'config':10} {'size':>9} {'min':>4} {'steps':>6} {'held-out PSNR':>13} {'SSIM':>6} "
        f"{'800x600 s':>9} {'RSS MiB':>8} {'load avg after':>16}"
    )
    print(header)
    print("-" * len(header))
    for r in results:
        size = f"{r['image_size'][0]}x{r['image_size'][1]}"
        print(
            f"{r['scene']:14} {r['configuration']:10} {size:>9} {r['minutes'] or 0:>4g} {r['steps']:>6} "
            f"{r['psnr']:>13.2f} {r['ssim']:>6.3f} {r['render_800x600_seconds']:>9.2f} "
            f"{r['peak_rss_mib']:>8.0f} {r['load_average_after_training']:>16}"
        )
    print()
    for r in results:
        images = ", ".join(f"{m['name']} {m['psnr']:.2f} dB" for m in r["per_image"])
        depth = r.get("depth_supervision") or {}
        depth_note = f"depth on {depth.get('rays')} rays" if depth.get("used") else "no depth"
        print(f"{r['scene']} {r['configuration']}: held-out {images}; {r['num_train_images']} train images; "
              f"{depth_note}")
        if r.get("psnr_on_black") is not None:
            print(f"{r['scene']} {r['configuration']} on black (without the photos' environment): held-out "
                  f"{r['psnr_on_black']:.2f} dB, SSIM {r['ssim_on_black']:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--configurations", nargs="+", default=list(CONFIGURATIONS), choices=CONFIGURATIONS)
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, default=10.0, help="training wall-clock per run")
    budget.add_argument("--steps", type=int, help="train each run this many steps instead (tuning)")
    parser.add_argument(
        "--variant", action="append", default=[], metavar="NAME=JSON",
        help="an extra configuration: NAME={TrainConfig fields as JSON} (e.g. model_options)",
    )  # fmt: skip
    parser.add_argument("--max-side", type=int, default=800, help="training image size (longer side)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (2 cores here)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda", "auto"])
    parser.add_argument(
        "--data-root", type=Path, default=DATA,
        help="the folder holding strecha/SCENE (unused for a scene whose OUT/sfm/SCENE exists)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("bench_nerf_real_runs"))
    parser.add_argument(
        "--side-by-side",
        action="store_true",
        help="train a scene's configurations at the same time, one process each (use --threads 1 on 2 "
        "cores): the same conditions for each, and one scene takes --minutes instead of twice that",
    )
    parser.add_argument("--no-frame", action="store_true", help="skip the timed 800x600 frame (ablations)")
    parser.add_argument(
        "--step-time", action="store_true",
        help="compare seconds per training step with Lego's instead (--steps steps each, interleaved)",
    )  # fmt: skip
    parser.add_argument("--single", nargs=2, metavar=("SCENE", "CONFIGURATION"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    configurations = with_variants({name: CONFIGURATIONS[name] for name in args.configurations}, args.variant)
    budget = {"steps": args.steps} if args.steps else {"minutes": args.minutes}

    if args.single:  # the subprocess of one (scene, configuration)
        import torch

        torch.set_num_threads(args.threads)
        scene, configuration = args.single
        settings = configurations[configuration]
        result = run_one(scene, configuration, settings, args.out, budget, args.max_side, args.device,
                         frame=not args.no_frame)
        (args.out / f"result_{scene}_{configuration}.json").write_text(json.dumps(result, indent=2))
        return

    args.out.mkdir(parents=True, exist_ok=True)
    print(f"== reconstructing (load average {load_average()})", flush=True)
    sfm = [reconstruct(scene, args.out, args.data_root) for scene in args.scenes]
    if args.step_time:
        import torch

        torch.set_num_threads(args.threads)
        steps = args.steps or STEP_TIME_STEPS
        print(f"== step time, {steps} steps (load average {load_average()})", flush=True)
        rows = step_time_comparison(
            args.scenes, configurations, args.out, args.max_side, steps, args.device, args.data_root / LEGO
        )
        (args.out / "step_time.json").write_text(json.dumps(rows, indent=2))
        print_step_times(rows)
        print(f"load average after: {load_average()}")
        return
    results = []
    for scene in args.scenes:
        for configuration in configurations:
            run_dir = args.out / scene / configuration
            if run_dir.exists():
                raise SystemExit(f"{run_dir} exists: choose another --out or remove it")
        # One group of subprocesses at a time: all of a scene's configurations with --side-by-side, else one.
        groups = [list(configurations)] if args.side_by_side else [[c] for c in configurations]
        for group in groups:
            print(f"== {scene} {' + '.join(group)} (load average {load_average()})", flush=True)
            common = [
                "--out", str(args.out), "--max-side", str(args.max_side), "--threads", str(args.threads),
                "--device", args.device, "--configurations", *args.configurations,
                *(["--steps", str(args.steps)] if args.steps else ["--minutes", str(args.minutes)]),
                *(f"--variant={spec}" for spec in args.variant), *(["--no-frame"] if args.no_frame else []),
            ]  # fmt: skip
            processes = [
                subprocess.Popen([sys.executable, __file__, "--single", scene, c, *common], cwd=REPO)
                for c in group
            ]
            for configuration, process in zip(group, processes, strict=True):
                if process.wait() != 0:
                    raise SystemExit(f"{scene} {configuration}: the training subprocess failed")
                results.append(json.loads((args.out / f"result_{scene}_{configuration}.json").read_text()))
    (args.out / "results.json").write_text(json.dumps({"sfm": sfm, "runs": results}, indent=2))
    print()
    print_table(sfm, results)


if __name__ == "__main__":
    main()
