"""The web app's pure modules (service/web/js/: PLY parsing, camera colours and paths, the novel view's
camera, formatting, URLs, upload file sorting) pass their unit tests under Node's built-in test runner
(tests/service/web/*.test.mjs). The PLY files the reconstruction writes are handed to them as fixtures."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from estimation.io.export import write_ply

JS_TESTS = sorted((Path(__file__).parent / "web").glob("*.test.mjs"))
NODE = shutil.which("node")
NODE_SECONDS = 120


@pytest.mark.skipif(NODE is None, reason="node is not installed: the web app JS tests need Node 20+")
def test_the_web_apps_pure_modules_pass_their_node_unit_tests(tmp_path):
    assert JS_TESTS, "no tests/service/web/*.test.mjs"
    rng = np.random.default_rng(0)
    points, colors = rng.normal(scale=5.0, size=(40, 3)), rng.integers(0, 256, size=(40, 3), dtype=np.uint8)
    write_ply(tmp_path / "points_binary.ply", points, colors, binary=True)
    write_ply(tmp_path / "points_ascii.ply", points, colors, binary=False)
    (tmp_path / "points.json").write_text(json.dumps({"points": points.tolist(), "colors": colors.tolist()}))

    result = subprocess.run(
        [NODE, "--test", *map(str, JS_TESTS)],
        capture_output=True,
        text=True,
        timeout=NODE_SECONDS,
        env={**os.environ, "SFMNERF_WEB_FIXTURES": str(tmp_path)},
    )
    assert result.returncode == 0, result.stdout[-20_000:] + result.stderr[-5_000:]
    assert "# skipped 0" in result.stdout and "# fail 0" in result.stdout, result.stdout[-5_000:]
