#!/usr/bin/env bash
# Set up, then run the main job on the bundled default: fit the paper's four-layer cup
# (configs/cup-fit.toml) to its bundled photographs (captures/samples/cup); the run folder is
# out/cup-fit/ (preset.toml, summary.json, report.html), replaced on each run of this script.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/layerfit fit configs/cup-fit.toml --out out/cup-fit --force "$@"
