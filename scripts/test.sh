#!/usr/bin/env bash
# Install what is missing, then run the whole test suite (slow end-to-end tests included) on every
# core (pytest-xdist; a module's tests stay on one worker so its fixtures are built once; the
# modules with slow tests first, as tests/conftest.py orders them).
# Extra arguments go to pytest: `bash scripts/test.sh -n 0 tests/unit` runs in one process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check railtraj plugins tests benchmarks
exec .venv/bin/python -m pytest -n auto --dist loadscope --no-loadscope-reorder --durations=15 "$@"
