#!/usr/bin/env bash
# Set up, then run the main job on the bundled default: make a synthetic 3-view capture of the
# glazed sphere (configs/glazed-sphere.toml, once) and fit its glaze back from a grey start
# (configs/glazed-sphere-fit.toml); results in out/glazed-sphere-fit/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if [ ! -f out/glazed-sphere-capture/capture.toml ]; then
    .venv/bin/layerfit synth configs/glazed-sphere.toml --scene configs/glazed-sphere-views.toml \
        --out out/glazed-sphere-capture
fi
.venv/bin/layerfit fit configs/glazed-sphere-fit.toml --out out/glazed-sphere-fit "$@"
