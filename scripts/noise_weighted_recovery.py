"""A lead, not the product: the recovery sweep's cases fitted with a noise-weighted loss.

Each pixel's residual is weighed by the inverse of its Monte Carlo variance (over `--renders`
renders of `--spp` at the truth, the mean of its channels, floored at the `--floor` percentile
of the object's pixels so that a quiet pixel cannot dominate); the `gn` phases see the weights,
Adam's phase at half resolution does not. Against a 256-spp target the inverse-variance bound of
alpha is 2-3x below the plain loss's (BENCHMARKS, "What the targets allow"); this asks how much
of that a fit gets. The weights come from the truth here, so a real fit would take them from
renders at its own estimate.

    .venv/bin/python scripts/noise_weighted_recovery.py sphere:0.01 torus:0.02 --seeds 0,1,2

A case is `shape:alpha`, or `shape:ior=2.8`. Prints each fit's errors, alpha's reported sd and
whether the sweep's targets are met (BENCHMARKS, "Low alpha: alternatives measured").
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from fit.variant import select_variant

select_variant()

import materials  # noqa: E402

materials.register()

from fit import recovery  # noqa: E402
from fit.material import resolve  # noqa: E402
from fit.solvers import DEFAULT_SCHEDULE, Problem, run_schedule  # noqa: E402


def parse_case(text: str) -> recovery.Case:
    shape, _, value = text.partition(":")
    if value.startswith("ior="):
        ior = float(value[4:])
        return recovery.Case(shape, ior=ior, label=f"ior {ior:g}")
    alpha = float(value)
    return recovery.Case(shape, roughness=alpha, label=f"alpha {alpha:g}")


def noise_scale(problem: Problem, case: recovery.Case, renders: int, spp: int, floor: float):
    """Per residual: 1 / the pixel's noise sd (floored), normalised to a mean square of 1."""
    _, sqrt_w = problem.target()
    truth = case.truth()
    x = np.concatenate([np.ravel(truth[k]) for k in recovery.KEYS]).astype(np.float32)
    images = np.array([problem.renderer().render(x, 1000 + k, spp) for k in range(renders)])
    variance = images.var(axis=0, ddof=1).reshape(-1, 3).mean(axis=1).repeat(3)
    valid = sqrt_w > 0
    lowest = np.percentile(variance[valid & (variance > 0)], floor)
    scale = 1.0 / np.sqrt(np.maximum(variance, lowest))
    return scale / np.sqrt(np.mean(scale[valid] ** 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cases", nargs="+", help="shape:alpha or shape:ior=VALUE")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--size", default="160x120")
    parser.add_argument("--renders", type=int, default=32)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--floor", type=float, default=90.0, help="percentile")
    args = parser.parse_args()
    width, height = (int(n) for n in args.size.split("x"))
    seeds = [int(s) for s in args.seeds.split(",")]
    for case in map(parse_case, args.cases):
        target = recovery.case_target(case, width, height)
        material = recovery.glaze(recovery.START)
        free = resolve(material, list(recovery.KEYS))
        scale = noise_scale(
            Problem(target, material, free), case, args.renders, args.spp, args.floor
        )
        for seed in seeds:
            problem = Problem(target, material, free)
            plain = problem.target

            def weighted(downscale=1, plain=plain, scale=scale):
                image, sqrt_w = plain(downscale)
                return image, sqrt_w * scale if downscale == 1 else sqrt_w

            problem.target = weighted
            began = time.perf_counter()
            result = run_schedule(problem, recovery.START, DEFAULT_SCHEDULE, seed)
            values = {k: result.values[k] for k in recovery.KEYS}
            out = recovery.Outcome(case, values, dict(result.std), time.perf_counter() - began)
            alpha = out.errors["glaze.roughness"] / case.roughness
            sd = out.std["glaze.roughness"] / case.roughness
            pigment = float(np.max(np.abs(out.errors["glaze.pigment"])))
            print(
                f"{case.name}, seed {seed}: alpha {100 * alpha:+.1f} % (sd {100 * sd:.1f} %), "
                f"ior {out.errors['glaze.ior']:+.4f}, pigment {pigment:.4f}, "
                f"within targets and 3 sd: {out.passed()}, {out.seconds:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
