#!/usr/bin/env bash
# Install what is missing, then run railtraj (by default on the built-in demo survey).
# Extra arguments are passed to railtraj, e.g.: bash scripts/demo.sh out_dir=/tmp/demo
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# The Ordnance Survey grids (needed for ETRS89 anchors) are not redistributed with railtraj; use
# the team's shared copy when it is there, unless the user already points at their own.
if [ -z "${RAILTRAJ_PROJ_GRID_DIR:-}" ] && [ -d ../shared/data/proj ]; then
  export RAILTRAJ_PROJ_GRID_DIR="$(cd ../shared/data/proj && pwd)"
fi
exec .venv/bin/railtraj "$@"
