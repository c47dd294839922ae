#!/usr/bin/env bash
# Install what is missing, then run the whole test suite (slow end-to-end tests included).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check railtraj plugins tests benchmarks
exec .venv/bin/python -m pytest "$@"
