"""`sfmnerf calibrate PHOTOS_DIR --board 9x6`: camera intrinsics from checkerboard photos."""

from __future__ import annotations

from pathlib import Path

import click


@click.command()
@click.argument("photos_dir", type=click.Path(path_type=Path))
@click.option("--board", default="9x6", show_default=True,
              help="Inner corners of the checkerboard, COLSxROWS (a board of 10x7 squares has 9x6).")
@click.option("--square-size", type=float, default=1.0, show_default=True,
              help="Side of one square (any unit); sets the unit of the board poses, not K.")
@click.option("--out", "out_dir", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Output folder (created); default: PHOTOS_DIR. Writes calibration.txt, distortion.json "
                   "and checkerboard_corners.png.")
@click.option("--max-detection-side", type=int, default=1000, show_default=True,
              help="Corners are detected on the photo downscaled to this side, then refined at full size.")
def calibrate(photos_dir: Path, board: str, square_size: float, out_dir: Path | None,
              max_detection_side: int) -> None:
    """Calibrate the camera (K and distortion k1 k2 p1 p2) from photos of a checkerboard in PHOTOS_DIR."""
    from estimation import InputError
    from estimation.calibration.checkerboard import calibrate_checkerboard, parse_board, write_calibration

    try:
        if square_size <= 0:
            raise InputError(f"--square-size must be positive, got {square_size}")
        result = calibrate_checkerboard(photos_dir, parse_board(board), square_size, max_detection_side)
        paths = write_calibration(result, photos_dir, out_dir or photos_dir)
    except InputError as error:
        raise click.ClickException(str(error)) from None
    except OSError as error:
        raise click.ClickException(f"cannot write the outputs: {error}") from None
    camera = result.camera
    click.echo(f"board found in {len(result.per_image_rms_px)}/{len(result.corners)} photos"
               + (f" (not in {', '.join(result.not_found)})" if result.not_found else ""))
    for name, rms in result.per_image_rms_px.items():
        click.echo(f"  {name}: reprojection RMS {rms:.3f} px")
    click.echo(f"fx {camera.fx:.3f}  fy {camera.fy:.3f}  cx {camera.cx:.3f}  cy {camera.cy:.3f}  "
               f"(OpenCV pixels: top-left pixel centre at 0,0)")
    click.echo(f"k1 {camera.k1:.5f}  k2 {camera.k2:.5f}  p1 {camera.p1:.5f}  p2 {camera.p2:.5f}  "
               f"RMS {result.rms_px:.3f} px")
    click.echo("wrote " + ", ".join(str(path) for path in paths.values()))
