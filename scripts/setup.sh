#!/usr/bin/env bash
# Create .venv (if needed) and install railtraj, its test tools and the example plugin into it.
# Idempotent: re-installs only when a pyproject.toml changed since the last successful run.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
  echo "railtraj needs Python >= 3.10 (found: $("$PY" --version 2>&1)); set PYTHON=/path/to/python3.11" >&2
  exit 1
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=.venv/.railtraj-installed
want=$(cat pyproject.toml plugins/railtraj-example/pyproject.toml | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing railtraj and its dependencies into .venv (first time: a few minutes)..."
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[test]" -e plugins/railtraj-example
  echo "$want" > "$stamp"
fi
# headless Chromium renders report.html in tests/integration/test_report_browser.py
if ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1 \
   && ! command -v google-chrome >/dev/null 2>&1 && [ -z "${RAILTRAJ_CHROMIUM:-}" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing chromium for the report's browser test (apt-get)..."
    export DEBIAN_FRONTEND=noninteractive
    apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1 \
      || { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends chromium >/dev/null; } \
      || echo "setup: could not install chromium; the report browser test will fail" >&2
  else
    echo "setup: no chromium found and apt-get needs root: install chromium (or set RAILTRAJ_CHROMIUM)" \
         "for tests/integration/test_report_browser.py" >&2
  fi
fi
