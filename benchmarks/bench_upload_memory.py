"""Upload bombs against a real server: the status each gets and the API process's peak memory (VmHWM).

`sfmnerf serve` runs in its own process (default settings, an admin token, a temporary data folder,
loopback). Each probe of issue 11 is posted with the token, then the server's peak resident memory so far
(/proc/PID/status VmHWM) and its current RSS are read. The heavy checks run in validation processes, so
the API's peak stays where start-up left it.

    python benchmarks/bench_upload_memory.py [--concurrent 1,8] [--baseline /path/to/other/checkout]
    python benchmarks/bench_upload_memory.py --address-space

Probes: a 40x2000x2000x3 float64 .npz of zeros (3.8 GB declared, ~0.5 MB on the wire), a 12000^2 PNG and
a 15000^2 PNG inside Blender dataset zips, and a 15000^2 PNG as a reconstruction image.

Then uploads at once (1 and 8 by default): the same count of 40x2000x2000x3 uint8 .npz of zeros (0.5 GB
declared, ~0.5 MB on the wire) and of the real lego_200 dataset zip (accepted: each is checked in a
validation process), while the resident memory of the API's whole process tree (the API, its validation,
render and job processes) is sampled every 20 ms. `--baseline` runs the same uploads against another
checkout's service in the same run, with `--baseline-concurrent` uploads at once (1 by default: without
the header checks each upload of zeros may take a validation process of several GB).

`--address-space`: the smallest SFMNERF_VALIDATION_MEMORY_BYTES (to 16 MiB) with which each check of the
real data passes, by bisection: what the validation process needs besides a dataset (VALIDATION_BASE_BYTES)
and how far the default is from what accepted datasets need.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the tests' server helpers

from tests.service.servers import descendants, free_port, start_server  # noqa: E402

TOKEN = "bench-token"
ZERO_CHUNK = bytes(2**20)


def npz_of_zeros(path: Path, shape: tuple[int, ...], dtype: str = "<f8") -> None:
    """An .npz whose images.npy is zeros of `shape`, streamed into the zip (never in memory)."""
    header = {"descr": dtype, "fortran_order": False, "shape": shape}
    text = repr(header).encode("latin1")
    text += b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
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


def tree_rss_mb(pid: int) -> float:
    """Resident memory of a process and all its descendants, MB (from /proc)."""
    total = 0.0
    for member in [pid, *descendants(pid)]:
        try:
            total += memory_mb(member)[1]
        except (OSError, KeyError):
            continue  # ended meanwhile
    return total


class TreePeak:
    """Samples the process tree's resident memory in a thread; `peak` is the largest sum seen."""

    def __init__(self, pid: int, period: float = 0.02) -> None:
        self.pid, self.period, self.peak = pid, period, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_rss_mb(self.pid))
            time.sleep(self.period)

    def __enter__(self) -> TreePeak:
        self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self._stop.set()
        self._thread.join()


def lego_200_zip() -> bytes:
    """The lego_200 Blender dataset as a client uploads it."""
    folder = ROOT.parent / "shared" / "data" / "lego_200"
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file() and path.suffix in (".png", ".json"):
                zf.write(path, f"lego_200/{path.relative_to(folder)}")
    return buffer.getvalue()


def concurrent_uploads(tmp: Path, root: Path, counts: list[int], uploads: dict[str, bytes]) -> None:
    """For each count: that many uploads of each kind at once; statuses and the tree's peak RSS."""
    port = free_port()
    server = start_server(tmp / f"data-{root.name}-{port}", port, root=root)
    headers = {"Authorization": f"Bearer {TOKEN}"}

    def post(name: str) -> int:
        files = [("dataset", (name, uploads[name], "application/octet-stream"))]
        response = httpx.post(
            f"http://127.0.0.1:{port}/v1/nerf", files=files, data={"steps": "1"}, headers=headers, timeout=600
        )
        if response.status_code == 202:  # only the check is measured: the job is not left to train
            httpx.delete(f"http://127.0.0.1:{port}/v1/jobs/{response.json()['id']}", headers=headers)
        return response.status_code

    try:
        idle = tree_rss_mb(server.pid)
        for name in uploads:
            for count in counts:
                started = time.monotonic()
                with TreePeak(server.pid) as peak, ThreadPoolExecutor(count) as pool:
                    statuses = Counter(pool.map(post, [name] * count))
                seconds = time.monotonic() - started
                shown = ", ".join(f"{n}x {status}" for status, n in sorted(statuses.items()))
                print(
                    f"| {root} | {count} x {name} ({len(uploads[name]) / 1024:.0f} KB) | {shown} | "
                    f"{seconds:.1f} | {idle:.0f} MB | {peak.peak:.0f} MB |"
                )
    finally:
        server.kill()
        server.wait()


def check_passes(check: str, arguments: dict, memory_mib: int, data_dir: Path) -> bool:
    from service.settings import WORKER_SETTINGS_ENV, ServiceSettings

    settings = ServiceSettings(data_dir=data_dir, validation_memory_bytes=memory_mib * 2**20)
    child = subprocess.run(
        [sys.executable, "-m", "service.validation", check, str(os.getpid())],
        input=json.dumps(arguments),
        capture_output=True,
        text=True,
        env={**os.environ, WORKER_SETTINGS_ENV: settings.to_worker_json(), "PYTHONPATH": str(ROOT),
             "OMP_NUM_THREADS": "1", "MALLOC_ARENA_MAX": "1"},  # as service.validation starts it
        cwd=ROOT,
    )
    return child.returncode == 0 and json.loads(child.stdout.splitlines()[-1])["status"] == 200


def address_space() -> None:
    """The smallest validation memory limit each check of the real data passes with (bisection)."""
    data = ROOT.parent / "shared" / "data"
    hall, fountain = data / "unity_hall", data / "strecha" / "fountain-P11"
    with tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp:
        photos = sorted(fountain.glob("*.jpg"))
        frames = [{"file_path": f"./{p.stem}", "transform_matrix": np.eye(4).tolist()} for p in photos]
        for photo in photos:
            (Path(tmp) / f"{photo.stem}.png").write_bytes(photo.read_bytes())
        meta = {"camera_angle_x": 0.8, "frames": frames}
        (Path(tmp) / "transforms_train.json").write_text(json.dumps(meta))
        cases = {
            "lego_tiny.npz (90 views of 100x100)": ("dataset", data / "lego_tiny.npz", data),
            "lego_200 (100 views of 200x200)": ("dataset", data / "lego_200", data / "lego_200"),
            "fountain-P11 as a dataset (11 views of 3072x2048)": ("dataset", Path(tmp), Path(tmp)),
        }
        print("\n| check | smallest SFMNERF_VALIDATION_MEMORY_BYTES that passes |\n|---|---|")
        for name, (check, path, within) in cases.items():
            arguments = {"path": str(path), "field": "dataset", "within": str(within)}
            print(f"| {name} | {smallest_limit_mib(check, arguments, Path(tmp))} MiB |", flush=True)
        images = sorted(p.name for p in hall.glob("*.png"))
        arguments = {"field": "images", "folder": str(hall), "images": images, "matches": [],
                     "image_ids": [], "width": 800, "height": 600}  # fmt: skip
        needed = smallest_limit_mib("reconstruction_inputs", arguments, Path(tmp))
        print(f"| Unity Hall photos (5 of 800x600) | {needed} MiB |")


def smallest_limit_mib(check: str, arguments: dict, data_dir: Path, low: int = 128, high: int = 4096) -> int:
    if not check_passes(check, arguments, high, data_dir):
        return -1
    while high - low > 16:
        middle = (low + high) // 2
        low, high = (low, middle) if check_passes(check, arguments, middle, data_dir) else (middle, high)
    return high


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--concurrent", default="1,8", help="upload counts at once, comma separated")
    parser.add_argument("--baseline", type=Path, help="another checkout to measure in the same run")
    parser.add_argument("--baseline-concurrent", default="1", help="upload counts at once for the baseline")
    parser.add_argument("--skip-probes", action="store_true", help="only the concurrent uploads")
    parser.add_argument("--address-space", action="store_true", help="only the validation memory bisection")
    arguments = parser.parse_args()
    if arguments.address_space:
        address_space()
        return
    print(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    os.environ["SFMNERF_API_TOKEN"] = TOKEN  # inherited by the server processes
    if not arguments.skip_probes:
        single_probes()
    counts = [int(n) for n in arguments.concurrent.split(",")]
    with tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp:
        zeros = Path(tmp) / "zeros-u8.npz"
        npz_of_zeros(zeros, (40, 2000, 2000, 3), "|u1")
        uploads = {"zeros-u8.npz": zeros.read_bytes(), "lego_200.zip": lego_200_zip()}
        print("\n| service | uploads at once | statuses | seconds | tree RSS idle | tree peak RSS |")
        print("|---|---|---|---|---|---|")
        concurrent_uploads(Path(tmp), ROOT, counts, uploads)
        if arguments.baseline:
            baseline_counts = [int(n) for n in arguments.baseline_concurrent.split(",")]
            concurrent_uploads(Path(tmp), arguments.baseline, baseline_counts, uploads)


def single_probes() -> None:
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
