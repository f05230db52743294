"""Which modules an import loads, seen from a fresh interpreter (this process has loaded everything)."""

import subprocess
import sys
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]


def import_loads(importing: str, module: str, then: str = "") -> bool:
    """True if `import importing` (and the statements `then`) in a fresh Python (run from the repository)
    puts `module` in sys.modules."""
    script = f"import sys, {importing}\n{then}\nprint({module!r} in sys.modules)"
    command = [sys.executable, "-c", script]
    run = subprocess.run(command, capture_output=True, text=True, check=True, cwd=REPOSITORY)
    return run.stdout.strip() == "True"
