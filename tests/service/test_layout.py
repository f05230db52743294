"""The job folder layout takes the packages' artefact names without loading what writes them: the API
process stays free of OpenCV, GTSAM and PyTorch."""

from __future__ import annotations

import subprocess
import sys

HEAVY_MODULES = ("cv2", "gtsam", "torch")


def test_the_layout_loads_no_heavy_library():
    probe = (
        "import sys, service.layout; "
        f"print([name for name in {HEAVY_MODULES!r} if name in sys.modules])"
    )
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert loaded.stdout.strip() == "[]"


def test_the_reconstruction_exports_are_the_files_the_pipeline_writes():
    from estimation.artefacts import PLY_NAME, TRANSFORMS_NAME
    from service.layout import RECONSTRUCTION_EXPORTS

    assert {PLY_NAME, TRANSFORMS_NAME} < set(RECONSTRUCTION_EXPORTS)
