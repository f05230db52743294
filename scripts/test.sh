#!/usr/bin/env bash
# Installs everything the test suite needs on a fresh machine, then runs it.
# torch is pinned so that machines with a local CPU wheel of 2.13.0 use it; elsewhere pip takes PyPI's.
set -euo pipefail
cd "$(dirname "$0")/.."
# The Celery tests run against a real Redis broker, the job-store tests against a real PostgreSQL too,
# the web app's tests in Debian's headless Chromium (driven by Playwright; screenshots in test-artifacts/).
missing=()
command -v redis-server >/dev/null 2>&1 || missing+=(redis-server)
compgen -G "/usr/lib/postgresql/*/bin/initdb" >/dev/null || missing+=(postgresql)
[ -x /usr/bin/chromium ] || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
    sudo=""; [ "$(id -u)" = 0 ] || sudo=sudo
    $sudo apt-get update -qq && $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi
python3 -m pip install -q "torch==2.13.0" -e ".[dev]"
python3 -m ruff check .
python3 -m pytest -n 2 "$@"
