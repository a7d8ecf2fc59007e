#!/usr/bin/env bash
# Regenerate the bundled cup capture (captures/samples/cup): five thin-lens photographs of the
# paper's four-layer cup (configs/cup.toml, the truth kept in the manifest's [truth]) seen by the
# cameras of configs/cup-views.toml, as 16-bit PNG with shot and read noise and random exposure
# offsets per view. Run from anywhere after scripts/setup.sh; replaces the folder atomically.
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=captures/samples/.cup-new
rm -rf "$tmp"
.venv/bin/layerfit synth configs/cup.toml --scene configs/cup-views.toml --out "$tmp" \
    --format png --spp ${SPP:-1024} --seed 7 --shot 0.0004 --read 0.0015 --exposure-ev 0.4 --exposure-base -2.3
rm -rf captures/samples/cup
mv "$tmp" captures/samples/cup
du -sh captures/samples/cup
