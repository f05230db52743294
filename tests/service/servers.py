"""Real `sfmnerf serve` processes on loopback, for the service tests and its benchmark."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import IO

import httpx

ROOT = Path(__file__).resolve().parents[2]
SERVER_START_SECONDS = 60.0


def free_port() -> int:
    """A loopback port that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(
    data_dir: Path,
    port: int,
    root: Path = ROOT,
    settings: dict[str, str] | None = None,
    log: IO[bytes] | None = None,
) -> subprocess.Popen:
    """`sfmnerf serve` in its own process, as a user runs it; returns once /readyz answers 200.

    `root`: the source tree whose service runs (another checkout, to compare versions in one benchmark);
    `settings`: SFMNERF_* environment variables for it; `log`: where its stdout and stderr go (default:
    nowhere). It leads its own process group, so a test can kill it with every process it started."""
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from service.cli import main; main()",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--data-dir",
            str(data_dir),
            "--log-level",
            "warning",
        ],
        cwd=root,
        env={**os.environ, **(settings or {}), "PYTHONPATH": str(root)},
        stdout=log or subprocess.DEVNULL,
        stderr=subprocess.STDOUT if log else subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + SERVER_START_SECONDS
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return process
        except httpx.HTTPError:
            pass
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with status {process.returncode}")
        time.sleep(0.2)
    process.kill()
    raise RuntimeError("the server did not become ready")
