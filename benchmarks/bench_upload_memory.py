"""Upload bombs against a real server: the status each gets and the API process's peak memory (VmHWM).

`sfmnerf serve` runs in its own process (default settings, an admin token, a temporary data folder,
loopback). Each probe of issue 11 is posted with the token, then the server's peak resident memory so far
(/proc/PID/status VmHWM) and its current RSS are read. The heavy checks run in validation processes, so
the API's peak stays where start-up left it.

    python benchmarks/bench_upload_memory.py

Probes: a 40x2000x2000x3 float64 .npz of zeros (3.8 GB declared, ~0.5 MB on the wire), a 12000^2 PNG and
a 15000^2 PNG inside Blender dataset zips, and a 15000^2 PNG as a reconstruction image.
"""

from __future__ import annotations

import io
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the tests' server helpers

from tests.service.servers import free_port, start_server  # noqa: E402

TOKEN = "bench-token"
ZERO_CHUNK = bytes(2**20)


def npz_of_zeros(path: Path, shape: tuple[int, ...]) -> None:
    """An .npz whose images.npy is float64 zeros of `shape`, streamed into the zip (never in memory)."""
    header = {"descr": "<f8", "fortran_order": False, "shape": shape}
    text = repr(header).encode("latin1")
    text += b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    size = int(np.prod(shape)) * 8
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("images.npy", "w", force_zip64=True) as member:
            member.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text)
            for _ in range(size // len(ZERO_CHUNK)):
                member.write(ZERO_CHUNK)
            member.write(bytes(size % len(ZERO_CHUNK)))
        for name, array in (("poses", np.tile(np.eye(4), (shape[0], 1, 1))), ("focal", np.array(100.0))):
            buffer = io.BytesIO()
            np.save(buffer, array)
            zf.writestr(f"{name}.npy", buffer.getvalue())


def png_of(side: int) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (side, side)).save(buffer, format="PNG")
    return buffer.getvalue()


def dataset_zip(png: bytes) -> bytes:
    frames = [{"file_path": "./train/r_0", "transform_matrix": np.eye(4).tolist()}]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("transforms_train.json", json.dumps({"camera_angle_x": 0.69, "frames": frames}))
        zf.writestr("train/r_0.png", png)
    return buffer.getvalue()


def memory_mb(pid: int) -> tuple[float, float]:
    """(peak RSS, current RSS) of a process in MB, from /proc/PID/status."""
    fields = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line
    )
    return int(fields["VmHWM"].split()[0]) / 1024, int(fields["VmRSS"].split()[0]) / 1024


def main() -> None:
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    with tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp:
        npz = Path(tmp) / "zeros.npz"
        npz_of_zeros(npz, (40, 2000, 2000, 3))
        png_12000, png_15000 = png_of(12000), png_of(15000)
        probes = [
            ("nerf", "dataset", "zeros.npz", npz.read_bytes()),
            ("nerf", "dataset", "png12000.zip", dataset_zip(png_12000)),
            ("nerf", "dataset", "png15000.zip", dataset_zip(png_15000)),
            ("reconstructions", "images", "15000.png", png_15000),
        ]
        del png_12000, png_15000
        os.environ["SFMNERF_API_TOKEN"] = TOKEN  # inherited by the server process
        port = free_port()
        server = start_server(Path(tmp) / "data", port)
        try:
            base = f"http://127.0.0.1:{port}"
            headers = {"Authorization": f"Bearer {TOKEN}"}
            peak, rss = memory_mb(server.pid)
            print("\n| probe | upload size | status | seconds | API peak RSS (VmHWM) | API RSS after |")
            print("|---|---|---|---|---|---|")
            print(f"| (after start-up) | | | | {peak:.0f} MB | {rss:.0f} MB |")
            for route, field, name, content in probes:
                files = [(field, (name, content, "application/octet-stream"))]
                if route == "reconstructions":
                    files.append((field, ("2.png", content, "application/octet-stream")))
                started = time.monotonic()
                response = httpx.post(
                    f"{base}/v1/{route}",
                    files=files,
                    data={"K": "1 0 1 0 1 1 0 0 1"} if field == "images" else {},
                    headers=headers,
                    timeout=600,
                )
                seconds = time.monotonic() - started
                peak, rss = memory_mb(server.pid)
                print(
                    f"| {name} -> /v1/{route} | {len(content) / 1024:.0f} KB | {response.status_code} | "
                    f"{seconds:.1f} | {peak:.0f} MB | {rss:.0f} MB |"
                )
                print(f"|   detail: {response.json().get('detail', '')[:150]} |||||")
            jobs_left = sorted(p.name for p in (Path(tmp) / "data" / "jobs").iterdir())
            print(f"\njob folders left: {jobs_left}")
        finally:
            server.kill()
            server.wait()


if __name__ == "__main__":
    main()
