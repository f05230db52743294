"""A novel view of a trained run beside the photo taken nearest to it (the README's figure).

    python3 scripts/novel_view_figure.py RUN_DIR RECONSTRUCTION_DIR OUT.jpg [--frames 48] [--width 800]

The view is the frame of the run's video path through the cameras (`neural.inference.camera_path`) that lies
farthest from every photo's centre, away from the path's ends; the photo is the one whose centre is nearest
to it, read from the reconstruction's transforms.json (the frame of the path's poses).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from neural.inference import camera_path, load_run, render_frame, to_uint8, view_camera

#: Frames at each end of the path left out: there it starts and ends on a photo.
PATH_END_FRAMES = 5
CAPTION_HEIGHT, GAP = 28, 8


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("reconstruction_dir", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--width", type=int, default=800)
    args = parser.parse_args()

    transforms = json.loads((args.reconstruction_dir / "transforms.json").read_text())
    centres = np.array([frame["transform_matrix"] for frame in transforms["frames"]])[:, :3, 3]
    path = np.array(camera_path(args.run_dir, args.frames)["path"])
    gaps = np.array([np.linalg.norm(centres - pose[:3, 3], axis=1).min() for pose in path])
    inner = slice(PATH_END_FRAMES, len(path) - PATH_END_FRAMES)
    index = int(np.argmax(gaps[inner])) + PATH_END_FRAMES
    nearest = int(np.argmin(np.linalg.norm(centres - path[index][:3, 3], axis=1)))

    run = load_run(args.run_dir, device="cpu")
    width, height = args.width, round(args.width * transforms["h"] / transforms["w"])
    view = to_uint8(render_frame(run, path[index], view_camera(run, width, height, None, None)).rgb)
    photo_path = args.reconstruction_dir / transforms["frames"][nearest]["file_path"]
    photo = Image.open(photo_path).convert("RGB").resize((width, height))
    held_out = set(json.loads((args.run_dir / "config.json").read_text())["cameras"].get("held_out", []))

    canvas = Image.new("RGB", (2 * width + GAP, height + CAPTION_HEIGHT), "white")
    canvas.paste(Image.fromarray(view), (0, CAPTION_HEIGHT))
    canvas.paste(photo, (width + GAP, CAPTION_HEIGHT))
    draw = ImageDraw.Draw(canvas)
    caption = f"novel view: frame {index} of {len(path)} on the path through the cameras"
    draw.text((6, 8), caption, fill="black")
    role = "held out" if nearest in held_out else "a training photo"
    draw.text((width + GAP + 6, 8), f"nearest photo: {photo_path.name} ({role})", fill="black")
    canvas.save(args.out, quality=88)
    print(f"frame {index}, nearest photo {photo_path.name}, {gaps[index]:.3f} units from it")


if __name__ == "__main__":
    main()
