#!/usr/bin/env bash
# Set up (with the test tools, and chromium for the HTML report test), then run the default test
# suite (under 10 minutes on 2 cores). `--slow` runs the heavy cases.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--slow" ]; then
  shift
  bash scripts/setup.sh --with-tests --with-chromium --with-blender --with-xvfb
  exec .venv/bin/python -m pytest -m slow "$@"
fi
bash scripts/setup.sh --with-tests --with-chromium
exec .venv/bin/python -m pytest "$@"
