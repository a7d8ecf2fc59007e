#!/usr/bin/env bash
# Set up, then run the main job on the bundled default. Until the fitter exists: render the glazed
# sphere of configs/glazed-sphere.toml to out/glazed-sphere.png (and .exr).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/layerfit render configs/glazed-sphere.toml --out out/glazed-sphere.png "$@"
