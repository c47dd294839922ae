#!/usr/bin/env bash
# Install what is missing, then run railtraj (by default on the built-in demo survey).
# Extra arguments are passed to railtraj, e.g.: bash scripts/demo.sh out_dir=/tmp/demo
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The Ordnance Survey grids for ETRS89 anchors: railtraj installs them on first use (railtraj.crs).
exec .venv/bin/railtraj "$@"
