"""`sfmnerf scene PHOTOS_DIR --out OUT`: photos to novel views in one process (service.pipeline.run_scene,
the pipeline POST /v1/scenes runs as child jobs).

OUT/reconstruction (as `sfmnerf reconstruct`), OUT/nerf (the run folder), OUT/orbit (the video's frames and
orbit.gif, along the cameras) and OUT/held_out (renders of the held-out views and metrics.json); one progress
bar per stage.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import click

from service.pipeline import ProgressCallback

STAGE_BAR_FORMAT = "{desc:<15} {bar} {n:5.1f}% [{elapsed}]"


@click.command()
@click.argument("photos_dir", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder: reconstruction/, nerf/, orbit/, held_out/.",
)
@click.option("--minutes", type=float, default=None, help="NeRF training time (default: the model's steps).")
@click.option("--steps", type=int, default=None, help="NeRF steps instead of --minutes.")
@click.option("--model", type=click.Choice(["vanilla", "fast"]), default="fast", show_default=True)
@click.option(
    "--calibration",
    type=click.Path(path_type=Path),
    default=None,
    help="3x3 K file; default: calibration.txt in PHOTOS_DIR.",
)
@click.option("--features", type=click.Choice(["auto", "matches", "sift"]), default="auto", show_default=True)
@click.option("--options", default=None, help="More NeRF TrainConfig fields as a JSON object.")
@click.option("--min-registered-images", type=int, default=None, help="Fewest registered images (default 3).")
@click.option("--orbit-frames", type=int, default=None,
              help="Most frames of the video (default 36; fewer when the views would take more than "
              "--views-share of the training time).")  # fmt: skip
@click.option("--train-max-side", type=int, default=None,
              help="Long side of the training photos (default: what the budget can train, from a timed "
              "probe; recorded in nerf/config.json as train_size).")  # fmt: skip
@click.option("--render-max-side", type=int, default=None,
              help="Largest long side of the video and held-out renders (default 200; smaller when the "
              "views would take more than --views-share of the training time).")  # fmt: skip
@click.option("--max-side", "deprecated_max_side", type=int, default=None, hidden=True,
              help="Deprecated: --render-max-side.")  # fmt: skip
@click.option("--views-share", type=float, default=None,
              help="The views stage takes at most this share of the training time (default 0.2; 0: no "
              "limit).")  # fmt: skip
def scene(
    photos_dir: Path,
    out_dir: Path,
    minutes: float | None,
    steps: int | None,
    model: str,
    calibration: Path | None,
    features: str,
    options: str | None,
    min_registered_images: int | None,
    orbit_frames: int | None,
    train_max_side: int | None,
    render_max_side: int | None,
    deprecated_max_side: int | None,
    views_share: float | None,
) -> None:
    """Reconstruct the photos in PHOTOS_DIR (or a video file's keyframes), train a NeRF on the poses, render
    a video along the cameras and the held-out views."""
    from pydantic import ValidationError
    from tqdm import tqdm

    from estimation import InputError, ReconstructionConfig
    from estimation.io.images import IMAGE_SUFFIXES
    from neural import TrainConfig
    from neural.budget import expected_seconds
    from neural.errors import CheckpointError, DatasetError
    from service.pipeline import SceneOptions, StageFailed, run_scene

    if deprecated_max_side is not None:
        click.echo("warning: --max-side is deprecated; it is --render-max-side", err=True)
        render_max_side = render_max_side if render_max_side is not None else deprecated_max_side
    try:
        extra = json.loads(options) if options else {}
        sizes = {"max_side": train_max_side} if train_max_side is not None else {}
        config = TrainConfig.model_validate(
            {**extra, **sizes, "model": model, "steps": steps, "minutes": minutes}
        )
        given = {"min_registered_images": min_registered_images, "orbit_frames": orbit_frames,
                 "orbit_max_side": render_max_side, "held_out_max_side": render_max_side,
                 "views_share": views_share}  # fmt: skip
        scene_options = SceneOptions(
            train_config=config.model_dump(mode="json"), **{k: v for k, v in given.items() if v is not None}
        )
    except (ValueError, ValidationError) as error:
        raise click.ClickException(f"options: {error}") from None

    if photos_dir.is_dir():  # a video's keyframes are counted only once they are extracted
        photos = [path for path in photos_dir.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES]
        expected = expected_seconds(config.minutes, len(photos), scene_options.views_share)
        if expected is not None:
            stages = ", ".join(f"{name} {value:.0f} s" for name, value in expected.items())
            click.echo(f"expected: {stages} (CPU)")

    @contextmanager
    def stage_bar(name: str) -> Iterator[ProgressCallback]:
        with tqdm(total=100, desc=name, bar_format=STAGE_BAR_FORMAT) as bar:
            yield lambda _text, fraction: bar.update(round(100 * min(max(fraction, 0.0), 1.0), 1) - bar.n)

    try:
        reconstruction_config = ReconstructionConfig(features=features, calibration=calibration)
        outcome = run_scene(photos_dir, out_dir, reconstruction_config, scene_options, stage_bar)
    except (InputError, DatasetError, CheckpointError, StageFailed) as error:
        raise click.ClickException(str(error)) from None
    report, held_out = outcome.report, outcome.held_out
    click.echo(
        f"registered {report['images_registered']}/{report['images_total']} images; "
        f"NeRF {outcome.trained.step} steps in {outcome.trained.seconds:.0f} s; orbit {outcome.video}; "
        f"held-out views {len(held_out.per_image)}, mean PSNR {held_out.mean_psnr:.2f} dB, "
        f"SSIM {held_out.mean_ssim:.3f}"
    )
    seconds = ", ".join(f"{name} {value:.1f}" for name, value in outcome.seconds.items())
    click.echo(f"seconds per stage: {seconds}")
