"""`sfmnerf nerf train | render | eval`: neural radiance fields from the command line.

The neural package (and with it torch) is imported inside each command, so `sfmnerf --help` stays fast.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, get_args

import click

from neural.config import ModelName

if TYPE_CHECKING:
    from neural.inference import PinholeIntrinsics

USER_ERRORS: tuple[type[Exception], ...] = (ValueError, FileNotFoundError)  # DatasetError/CheckpointError too


@click.group()
def nerf() -> None:
    """Neural radiance fields: train, render, eval."""


@nerf.command("train")
@click.argument("data", type=click.Path(exists=True, path_type=Path))
@click.option("--out", "run_dir", required=True, type=click.Path(path_type=Path), help="Run folder to write.")
@click.option("--model", type=click.Choice(list(get_args(ModelName))), default=None, help="Default: fast.")
@click.option("--steps", type=int, default=None, help="Optimisation steps (default: the model's).")
@click.option("--minutes", type=float, default=None, help="Train for this long instead of a step count.")
@click.option("--batch-rays", type=int, default=None, help="Rays per step (default: the model's).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="Default: auto.")
@click.option("--seed", type=int, default=None, help="Random seed (default 0).")
@click.option("--lr", type=float, default=None, help="Initial learning rate (default: the model's).")
@click.option("--checkpoint-every", type=int, default=None, help="Steps between checkpoints (default 500).")
@click.option("--val-every", type=int, default=None, help="Steps between validation renders (default 500).")
@click.option(
    "--chunk-rays", type=int, default=None, help="Rays rendered at once; lower it on out-of-memory."
)
@click.option("--precrop-steps", type=int, default=None, help="First steps drawing rays from image centres.")
@click.option("--background", type=click.Choice(["white", "black", "random"]), default=None,
              help="Behind the scene (default: white for Blender/npz, random for photographs).")  # fmt: skip
@click.option("--render-environment/--no-render-environment", default=None,
              help="Renders of a random-background run show the photos' colours by direction where the "
              "field is empty (default: on; off: black).")  # fmt: skip
@click.option("--unbounded/--bounded", default=None,
              help="Content beyond the scene box, contracted (default: unbounded for photos).")  # fmt: skip
@click.option("--max-side", type=int, default=None, help="Train on images shrunk to this longer side (px).")
@click.option("--downscale", type=float, default=None, help="Train on images shrunk by this factor.")
@click.option("--depth-supervision/--no-depth-supervision", default=None,
              help="Depth loss on a reconstruction's sparse points (default: on for them).")  # fmt: skip
@click.option("--photo-appearance/--no-photo-appearance", default=None,
              help="Learn a colour transform per training photo (default: off).")  # fmt: skip
@click.option("--resume", is_flag=True, help="Continue the run in --out from its latest checkpoint.")
def train_command(data: Path, run_dir: Path, resume: bool, **options: Any) -> None:
    """Train a radiance field on DATA (Blender folder, tiny-NeRF .npz or `sfmnerf reconstruct` output)."""
    from tqdm import tqdm

    from neural import TrainConfig, train

    given = {name: value for name, value in options.items() if value is not None}
    try:
        config = TrainConfig(**given) if (given or not resume) else None
    except USER_ERRORS as error:
        raise click.ClickException(str(error)) from None
    bar = tqdm(total=100, desc="train", bar_format="{l_bar}{bar}| {elapsed}<{remaining} {postfix}")

    def on_progress(stage: str, fraction: float) -> None:
        bar.update(round(100 * fraction) - bar.n)

    def on_metrics(record: dict[str, Any]) -> None:
        if "loss" in record:
            bar.set_postfix(step=record["step"], loss=f"{record['loss']:.4f}", psnr=f"{record['psnr']:.2f}")
        else:
            bar.write(f"step {record['step']}: validation PSNR {record['val_psnr']:.2f} dB")

    try:
        result = train(
            data, run_dir, config, resume=resume, progress=on_progress, metrics_callback=on_metrics
        )
    except USER_ERRORS as error:
        raise click.ClickException(str(error)) from None
    finally:
        bar.close()
    best = "n/a" if result.best_val_psnr is None else f"{result.best_val_psnr:.2f} dB"
    click.echo(
        f"trained {result.step} steps in {result.seconds:.0f} s (stopped by {result.stopped_by}); "
        f"last batch PSNR {result.final_psnr:.2f} dB, best validation PSNR {best}; "
        f"checkpoint {result.latest_checkpoint}"
    )


def frames_from_transforms(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The JSON object and its frames, each with file_path and a rigid 4x4 transform_matrix."""
    from neural.data import check_rigid_pose, read_json, require

    meta = read_json(path)
    frames = require(meta, "frames", path)
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: 'frames' is empty")
    checked = []
    for index, frame in enumerate(frames):
        where = f"{path} frames[{index}]"
        checked.append(
            {
                "file_path": str(require(frame, "file_path", where)),
                "c2w": check_rigid_pose(require(frame, "transform_matrix", where), where),
            }
        )
    return meta, checked


def camera_for_transforms(
    default: PinholeIntrinsics, meta: dict[str, Any], path: Path | str
) -> PinholeIntrinsics:
    """The intrinsics a transforms JSON asks for, at the default camera's (requested) size.

    fx: fl_x scaled from the file's width w, else 0.5 W / tan(camera_angle_x / 2), else the default's;
    fy: fl_y scaled from h, else fx; cx, cy: scaled from w, h when given, else the image centre.
    """
    width, height = default.width, default.height
    sx = width / float(meta["w"]) if "w" in meta else None
    sy = height / float(meta["h"]) if "h" in meta else None
    if "fl_x" in meta and sx is None:
        raise ValueError(f"{path}: 'fl_x' needs 'w' (the width it is given for) to be scaled")
    if "fl_x" in meta:
        fx = float(meta["fl_x"]) * sx
    elif "camera_angle_x" in meta:
        fx = 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))
    else:
        fx = default.fx
    fy = float(meta["fl_y"]) * sy if "fl_y" in meta and sy is not None else fx
    cx = float(meta["cx"]) * sx if "cx" in meta and sx is not None else width / 2.0
    cy = float(meta["cy"]) * sy if "cy" in meta and sy is not None else height / 2.0
    return replace(default, fx=fx, fy=fy, cx=cx, cy=cy)


@nerf.command("render")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "--poses", type=click.Path(exists=True, dir_okay=False, path_type=Path), help="transforms JSON."
)
@click.option(
    "--orbit", type=int, default=None, help="Render a video of this many frames instead (see --path)."
)
@click.option("--view", is_flag=True, help="Render the default view instead: the photo nearest the middle of "
              "the camera path (OUT/view.png).")  # fmt: skip
@click.option("--path", "video_path", type=click.Choice(["captured", "orbit"]), default="captured",
              show_default=True, help="The video's path: through the registered cameras, or a circle round "
              "the scene.")  # fmt: skip
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--width", type=int, default=None, help="Default: the training images' width.")
@click.option("--height", type=int, default=None, help="Default: the poses file's aspect.")
@click.option("--depth", is_flag=True, help="Also write <name>_depth.png (near bright, far dark).")
@click.option("--checkpoint", default="latest", show_default=True, help="latest, best or a step number.")
@click.option("--format", "video_format", type=click.Choice(["gif", "mp4"]), default="gif", show_default=True)
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
def render_command(
    run_dir: Path,
    poses: Path | None,
    orbit: int | None,
    view: bool,
    video_path: str,
    out_dir: Path,
    width: int | None,
    height: int | None,
    depth: bool,
    checkpoint: str,
    video_format: str,
    device: str,
) -> None:
    """Render the views of a transforms JSON (one PNG per frame, named after file_path), a video along the
    cameras, or the default view."""
    if [poses is not None, orbit is not None, view].count(True) != 1:
        raise click.UsageError("give exactly one of --poses TRANSFORMS_JSON, --orbit N or --view")
    from PIL import Image
    from tqdm import tqdm

    from neural.inference import (
        check_sees_scene,
        depth_to_uint8,
        load_run,
        render_frame,
        render_orbit,
        to_uint8,
        view_camera,
    )

    try:
        if orbit is not None:
            bar = tqdm(total=orbit, desc="orbit", unit="frame")
            video = render_orbit(
                run_dir, orbit, out_dir, width, height, video_format=video_format, checkpoint=checkpoint,
                progress=lambda stage, fraction: bar.update(round(fraction * orbit) - bar.n), device=device,
                path=video_path,
            )  # fmt: skip
            bar.close()
            click.echo(f"wrote {orbit} frames and {video}")
            return
        run = load_run(run_dir, checkpoint, device=device)
        if view:
            width = width or run.camera.width
            height = height or round(width * run.camera.height / run.camera.width)
            rendered = check_sees_scene(render_frame(run, None, view_camera(run, width, height, None, None)))
            out_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(to_uint8(rendered.rgb)).save(out_dir / "view.png")
            click.echo(f"wrote the default view ({width}x{height}) to {out_dir / 'view.png'}")
            return
        meta, frames = frames_from_transforms(poses)
        width = width or run.camera.width  # the training size: a photo's transforms.json has its full size
        aspect = float(meta["h"]) / float(meta["w"]) if "w" in meta and "h" in meta else None
        height = height or round(width * (aspect or run.camera.height / run.camera.width))
        camera = camera_for_transforms(view_camera(run, width, height, None, None), meta, poses)
        out_dir.mkdir(parents=True, exist_ok=True)
        for frame in tqdm(frames, desc="render", unit="frame"):
            stem = Path(frame["file_path"]).stem
            rendered = render_frame(run, frame["c2w"], camera)
            Image.fromarray(to_uint8(rendered.rgb)).save(out_dir / f"{stem}.png")
            if depth:
                Image.fromarray(depth_to_uint8(rendered.depth, run.scene)).save(out_dir / f"{stem}_depth.png")
    except USER_ERRORS as error:
        raise click.ClickException(str(error)) from None
    click.echo(f"wrote {len(frames)} frames ({width}x{height}) to {out_dir}")


@nerf.command("eval")
@click.argument("run_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "--data", required=True, type=click.Path(exists=True, path_type=Path), help="Dataset to test on."
)
@click.option("--split", default="val", show_default=True, help="train, val or test.")
@click.option("--checkpoint", default="latest", show_default=True, help="latest, best or a step number.")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Where to write the metrics; default RUN/eval_<split>.json.")  # fmt: skip
@click.option("--save-renders", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also save the rendered images here.")  # fmt: skip
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
def eval_command(
    run_dir: Path,
    data: Path,
    split: str,
    checkpoint: str,
    json_path: Path | None,
    save_renders: Path | None,
    device: str,
) -> None:
    """PSNR and SSIM of the run's renders of DATA's split (default: the held-out val views, never trained
    on), at the training image size; per image and mean, printed and saved as JSON. No LPIPS: its backbone
    weights cannot be installed offline (see docs/nerf.md)."""
    from neural import evaluate

    try:
        result = evaluate(run_dir, data, split, checkpoint=checkpoint, out_dir=save_renders, device=device)
    except USER_ERRORS as error:
        raise click.ClickException(str(error)) from None
    click.echo(f"{'image':<24} {'PSNR (dB)':>10} {'SSIM':>8}")
    for metrics in result.per_image:
        click.echo(f"{metrics.name:<24} {metrics.psnr:>10.2f} {metrics.ssim:>8.4f}")
    click.echo(f"{'mean':<24} {result.mean_psnr:>10.2f} {result.mean_ssim:>8.4f}")
    json_path = json_path or run_dir / f"eval_{split}.json"
    json_path.write_text(json.dumps(result.to_dict(), indent=2))
    click.echo(f"step {result.step}; wrote {json_path}")
