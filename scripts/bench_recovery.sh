#!/usr/bin/env bash
# The recovery sweep of BENCHMARKS.md: 30 synthetic glazes on a sphere and a torus
# fitted back with the default schedule; its calibration table into scripts/benchmarks/.
# Resumable: finished cases are kept in scripts/benchmarks/recovery.json (delete it to start
# again; a file of another size, schedule or start is refused). About 40 minutes on 2 cores.
# Usage: bash scripts/bench_recovery.sh [--size 160x120] [--shapes sphere,torus,cup]
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p scripts/benchmarks
exec .venv/bin/layerfit bench --only recovery \
    --results scripts/benchmarks/recovery.json --out scripts/benchmarks/recovery.md --force "$@"
