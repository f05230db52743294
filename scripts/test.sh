#!/usr/bin/env bash
# Installs everything the test suite needs on a fresh machine, then runs it.
# torch is pinned so that machines with a local CPU wheel of 2.13.0 use it; elsewhere pip takes PyPI's.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v redis-server >/dev/null 2>&1; then
    # The Celery tests run against a real Redis broker.
    if [ "$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq redis-server >/dev/null
    else sudo apt-get update -qq && sudo apt-get install -y -qq redis-server >/dev/null; fi
fi
python3 -m pip install -q "torch==2.13.0" -e ".[dev]"
python3 -m ruff check .
python3 -m pytest -n 2 "$@"
