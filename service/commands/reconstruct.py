"""`sfmnerf reconstruct IMAGES_DIR --out OUT` (or a video file instead of IMAGES_DIR): Structure from
Motion through `estimation.reconstruct`."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

PERCENT = 100
DESCRIPTION_WIDTH = 32


class StageProgressBars:
    """A `ProgressCallback` showing one tqdm bar per stage; each bar counts the overall percentage.

    A stage is named by the first word of the callback's text ("register 3.png" and "register 4.png"
    share the "register" bar, whose description follows the latest text).
    """

    def __init__(self) -> None:
        self.stage: str | None = None
        self.bar: tqdm | None = None

    def __call__(self, text: str, fraction: float) -> None:
        percent = round(PERCENT * min(max(fraction, 0.0), 1.0), 1)
        stage = text.split(maxsplit=1)[0] if text.strip() else text
        if stage != self.stage or self.bar is None:
            self.close()
            self.stage = stage
            self.bar = tqdm(total=PERCENT, initial=percent, desc=f"{text:<{DESCRIPTION_WIDTH}}",
                            bar_format="{desc} {bar} {n:5.1f}% [{elapsed}]", leave=True)
        else:
            self.bar.set_description_str(f"{text:<{DESCRIPTION_WIDTH}}", refresh=False)
            self.bar.update(max(percent - self.bar.n, 0.0))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> StageProgressBars:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


@click.command()
@click.argument("images_dir", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(path_type=Path, file_okay=False),
              help="Output folder (created): sparse/, points.ply, depths.npz, transforms.json, report.json, "
                   "figures/.")
@click.option("--calibration", type=click.Path(path_type=Path), default=None,
              help="3x3 K file; default: calibration.txt in IMAGES_DIR, and without one the camera is "
                   "calibrated from EXIF or a prior and refined.")
@click.option("--features", type=click.Choice(["auto", "matches", "sift"]), default="auto", show_default=True,
              help="auto: the folder's matching{i}.txt files when present, else SIFT.")
@click.option("--relative-pose", type=click.Choice(["five-point", "eight-point"]), default="five-point",
              show_default=True,
              help="five-point: E by the minimal 5-point solver in RANSAC; eight-point: the normalized "
                   "8-point F in RANSAC, then E = K^T F K.")
@click.option("--estimator", type=click.Choice(["numpy", "opencv"]), default="numpy", show_default=True,
              help="RANSAC of the pair geometry: numpy: the project's own LO-RANSAC; opencv: cv2's compiled "
                   "RANSAC, inliers re-scored by the project's residuals (faster, slightly less accurate).")
@click.option("--camera-model", type=click.Choice(["auto", "pinhole", "simple-radial", "radial", "opencv"]),
              default="auto", show_default=True,
              help="COLMAP camera model. auto: pinhole with a calibration file (K fixed), simple-radial "
                   "without one (focal length from EXIF or 1.2*max(w,h), refined with k1 by the bundle "
                   "adjustment).")
@click.option("--single-camera/--per-image-camera", default=True, show_default=True,
              help="One camera shared by all photos, or one per photo.")
@click.option("--refine-principal-point/--fixed-principal-point", default=None,
              help="Without a calibration file: refine cx, cy from the image centre, or hold them there "
                   "(default: refined for a shared camera, held for per-image cameras).")
@click.option("--all-models", is_flag=True,
              help="Also write every smaller model (images no model could join) to OUT/models/<k>/.")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="SIFT detection threads, then processes matching and verifying pairs (0: one per "
                   "available CPU core; 1: everything in this process).")
def reconstruct(images_dir: Path, out_dir: Path, calibration: Path | None, features: str, relative_pose: str,
                estimator: str, camera_model: str, single_camera: bool, refine_principal_point: bool | None,
                all_models: bool, workers: int) -> None:
    """Recover cameras and a coloured point cloud from the photographs in IMAGES_DIR, or from the
    keyframes of a video (IMAGES_DIR a .mp4/.mov/.mkv/.webm/.avi file: sharp frames chosen as the view
    moves, written to OUT/frames/)."""
    from estimation import InputError, ReconstructionConfig
    from estimation import reconstruct as run_reconstruction
    from estimation.config import CameraConfig, TwoViewConfig

    config = ReconstructionConfig(features=features, calibration=calibration,
                                  two_view=TwoViewConfig(relative_pose=relative_pose, estimator=estimator),
                                  camera=CameraConfig(model=camera_model, single_camera=single_camera,
                                                      refine_principal_point=refine_principal_point),
                                  mapper={"export_all_models": all_models}, sift={"workers": workers})
    try:
        with StageProgressBars() as progress:
            result = run_reconstruction(images_dir, out_dir, config, progress=progress)
    except InputError as error:
        raise click.ClickException(str(error)) from None
    except OSError as error:
        raise click.ClickException(f"cannot write the outputs: {error}") from None

    report = result.report
    if "video" in report:
        click.echo(video_line(report["video"]))
    after = report["reprojection_error_px"]["after_ba"]
    click.echo(
        f"registered {report['images_registered']}/{report['images_total']} images, "
        f"{report['points']} points, "
        f"reprojection error after BA: RMS {after['rms']:.3f} px, median {after['median']:.3f} px"
    )
    if len(report["models"]) > 1:
        sizes = ", ".join(str(model["images_registered"]) for model in report["models"])
        where = "OUT/models/<k>/" if all_models else "report.json (--all-models writes them)"
        click.echo(f"{len(report['models'])} models ({sizes} images); the largest is written, the others "
                   f"are in {where}")
    intrinsics = report["intrinsics"]
    camera = intrinsics.get("camera") or next(iter(intrinsics["cameras"].values()))
    click.echo(f"camera {intrinsics['model']} ({intrinsics['source']}): fx {camera['fx']:.2f} "
               f"fy {camera['fy']:.2f} cx {camera['cx']:.2f} cy {camera['cy']:.2f} k1 {camera['k1']:.4f} "
               f"k2 {camera['k2']:.4f}")
    test = intrinsics.get("principal_point_test")
    if test is not None:
        outcome = "kept" if test["kept"] else "not significant: held at the image centre"
        click.echo(f"principal point shift from the image centre ({test['shift_px'][0]:+.1f}, "
                   f"{test['shift_px'][1]:+.1f}) px, 1-sigma ({test['sigma_px'][0]:.1f}, "
                   f"{test['sigma_px'][1]:.1f}) px: {outcome}")
    for warning in report["warnings"]:
        click.echo(f"warning: {warning}")
    for entry in report["unregistered"]:
        click.echo(f"not registered: {entry['image']} ({entry['reason']})")
    click.echo(f"wrote {result.out_dir}/ (sparse/, points.ply, depths.npz, transforms.json, report.json, "
               f"figures/) in {report['seconds_total']:.1f} s")


def video_line(video: dict) -> str:
    """One line on a video input: frames decoded, blurred ones dropped, keyframes and the focal source."""
    focal = f"focal {video['focal_35mm']:g} mm (35 mm equivalent) from the container" \
        if video["focal_35mm"] is not None else "no focal length in the container"
    return (f"video {video['file']}: {video['frames_decoded']} frames, {video['blurred_frames']} blurred, "
            f"{video['keyframes']} keyframes in {video['frames_folder']}/; {focal}")
