#!/usr/bin/env bash
# The GPU check of BENCHMARKS.md: on a machine with an NVIDIA GPU and layerfit's
# dependencies importable by `python3` (a venv, or PYTHONPATH), run with `cuda_ad_rgb`:
#   1. a smoke render, 2. the profile table, 3. the default against the tutorial loop (2 seeds),
#   4. the bench grid at 128 wide, 5. the default test suite, 6. the rest of the grid (64 and
#   256 wide) while time is left.
# Each part has its own time limit and a failure does not stop the next; everything goes to $1.
# Usage: bash scripts/gpu_check.sh OUTDIR [SECONDS_FOR_THE_WHOLE]   (default 540)
# Run 2026-11-30 on an H200 (results in BENCHMARKS.md, "On a GPU"). There the image's own Python
# ran it, with Mitsuba, Dr.Jit, pydantic, OpenImageIO, rawpy and MaterialX carried as wheels (no
# Ray or USD: tests/fit/test_batch.py and the USD export tests were left out by hand).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: gpu_check.sh OUTDIR [SECONDS]}
budget=${2:-540}
mkdir -p "$out"
export LAYERFIT_VARIANT=cuda_ad_rgb LAYERFIT_DEBUG=1 PYTHONUNBUFFERED=1 COLUMNS=200
start=$(date +%s)
left() { echo $((budget - ($(date +%s) - start))); }
py=${PYTHON:-python3}

{
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    nproc; $py --version
    $py -c "import mitsuba, drjit, jax; print('mitsuba', mitsuba.__version__, 'drjit', \
drjit.__version__, 'jax', jax.__version__)"
} >"$out/machine.txt" 2>&1
cat "$out/machine.txt"

echo "== smoke ($(left) s left)"
timeout 120 $py - <<'EOF' 2>&1 | tee "$out/smoke.log"
import time
from fit.variant import select_variant
print("variant", select_variant())
import mitsuba as mi
import materials
materials.register()
t = time.perf_counter()
img = mi.render(mi.load_dict(mi.cornell_box()), spp=16)
print("cornell box 256x256 16 spp, first render incl. compile:", round(time.perf_counter() - t, 2), "s")
EOF

echo "== profile ($(left) s left)"
timeout 90 $py -m fit bench --only profile --size 160x120 --out "$out/profile.md" --force \
    2>&1 | tail -30

echo "== default vs tutorial loop, 2 seeds ($(left) s left)"
timeout 150 $py -m fit bench --only versus --seeds 2 --results "$out/versus.json" \
    --out "$out/versus.md" --force 2>&1 | tail -20

echo "== grid at 128 wide ($(left) s left)"
timeout 170 $py -m fit bench --only grid --shapes sphere --widths 128 \
    --results "$out/grid.json" 2>&1 | tail -40

echo "== tests ($(left) s left)"
# pytest-xdist and pytest-timeout where the machine has them; pytest-benchmark's warning under
# xdist would be an error here (the suite turns warnings into errors).
extra=()
$py -c "import xdist" 2>/dev/null && extra+=(-n 8)
$py -c "import pytest_timeout" 2>/dev/null && extra+=(--timeout 150)
timeout 200 $py -m pytest -q "${extra[@]}" -p no:cacheprovider -p no:benchmark \
    -W ignore::DeprecationWarning -W ignore::FutureWarning \
    2>&1 | tee "$out/tests.log" | tail -60

rest=$(($(left) - 15))
echo "== grid, the rest ($rest s)"
if [ "$rest" -gt 30 ]; then
    timeout "$rest" $py -m fit bench --only grid --shapes sphere,cup --widths 64,128,256 \
        --results "$out/grid.json" --out "$out/grid.md" --force 2>&1 | tail -60
fi
echo "== done after $(($(date +%s) - start)) s"
