#!/usr/bin/env bash
# The bench grid of BENCHMARKS.md: resolution x spp x solver on the sphere, the
# diagonal on the cup, the tutorial loop; its table and Pareto plot into scripts/benchmarks/.
# Resumable: finished cells are kept in scripts/benchmarks/grid.json (delete it to start again).
# Usage: bash scripts/bench_grid.sh [--widths 64,128,256]
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p scripts/benchmarks
exec .venv/bin/layerfit bench --only grid --shapes sphere,cup \
    --results scripts/benchmarks/grid.json --out scripts/benchmarks/grid.md --force "$@"
