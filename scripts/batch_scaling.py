"""Measure a batch of small fits with 1 and with 2 Ray workers (BENCHMARKS.md, "Batches").

Both timed runs find Dr.Jit's kernel cache warm (an untimed one-fit batch runs first).

Synthesises 4 captures of the glazed sphere (48x36, one view each, 4 synth seeds) and fits each
(pigment, alpha, ior; Adam 40 x 8 spp at half resolution, 30 x 16 spp) through
`layerfit batch --num-cpus N`, in a fresh process per N, and prints the wall time of the whole
command and each worker's peak memory (from the index). Run from the project root:
`.venv/bin/python scripts/batch_scaling.py [WORKDIR]` (default out/batch-scaling).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CONFIG = """capture = "caps/c0"
[material]
type = "glaze"
pigment = [0.3, 0.3, 0.3]
roughness = 0.2
ior = 1.3
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior"]
[[fit.phases]]
solver = "adam"
steps = 40
spp = 8
downscale = 2
lr = 0.1
[[fit.phases]]
solver = "adam"
steps = 30
spp = 16
lr = 0.03
average = 0.5
"""


def captures(folder: Path) -> list[str]:
    sys.path.insert(0, str(ROOT))
    from fit.variant import select_variant

    select_variant()
    import materials

    materials.register()
    from fit.commands.synth import synthesize
    from fit.config import load_render_config

    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=48, height=36)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    names = []
    for k in range(4):
        if not (folder / f"c{k}").exists():
            synthesize(scene, cfg.material, folder / f"c{k}", spp=256, seed=k)
        names.append(f"caps/c{k}")
    return names


def main() -> None:
    work = Path(sys.argv[1] if len(sys.argv) > 1 else "out/batch-scaling").resolve()
    names = captures(work / "caps")
    (work / "fit.toml").write_text(CONFIG)
    # untimed warm-up: one fit, so that every kernel is in Dr.Jit's disk cache for both runs
    (work / "warm.toml").write_text(
        f'configs = ["fit.toml"]\ncaptures = ["{names[0]}"]\nout = "runs-warm"\n'
    )
    subprocess.run(
        [sys.executable, "-m", "fit", "batch", str(work / "warm.toml")], cwd=ROOT, check=True
    )
    for cpus in (1, 2):
        spec = work / f"batch-{cpus}.toml"
        spec.write_text(
            f'configs = ["fit.toml"]\ncaptures = {json.dumps(names)}\nout = "runs-{cpus}"\n'
        )
        began = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "fit", "batch", str(spec), "--num-cpus", str(cpus)],
            cwd=ROOT,
            check=True,
        )
        wall = time.perf_counter() - began
        index = json.loads((work / f"runs-{cpus}" / "index.json").read_text())
        fits = index["fits"]
        rss = ", ".join(f"{f['max_rss_mb']:.0f}" for f in fits)
        per_fit = ", ".join(f"{f['wall_time_s']:.0f}" for f in fits)
        print(f"{cpus} worker(s): {wall:.0f} s; per fit {per_fit} s; worker peak RSS {rss} MB")


if __name__ == "__main__":
    main()
