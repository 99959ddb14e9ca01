#!/usr/bin/env bash
# Set up (if needed) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The viewer test drives a real headless Chromium (Debian packages; nothing is downloaded at test time).
{ command -v chromium && command -v chromedriver; } >/dev/null || (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null)
# One test process per core, each module on one process (its fixtures are built once), one thread each; the modules
# in the order of their cost marks (tests/conftest.py), not reordered by their number of tests.
export OMP_NUM_THREADS=1
exec .venv/bin/python -m pytest -q -n auto --dist loadscope --no-loadscope-reorder tests "$@"
