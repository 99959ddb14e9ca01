#!/usr/bin/env bash
# Set up (if needed) and run the demo on a generated synthetic scene; prints where the results are.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/ns-gear-demo "$@"
