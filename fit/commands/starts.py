"""Multi-start: one fit's schedule run from several starts on Ray workers, the best kept.

Start 0 is the configured start. The other K-1 are a Latin hypercube of normal quantiles with
standard deviation `fit.start_spread`, in the solvers' unconstrained space (sigmoid: logits),
around the configured start with each component's centre first pulled inside |u| <= 2: a start at
a bound sits on its sigmoid's flat end (ior 1.01 is u = -6.9), where a spread of a few units would
leave every start at the bound. Per-view gains start at 1 and textures as configured (not spread).

Each start runs the whole schedule (and its uncertainty) in its own worker, then scores its answer
by a common loss: `fit.starts_spp` samples per pixel at full resolution with one seed shared by
all starts (common random numbers), so the comparison is not decided by Monte Carlo noise."""

from __future__ import annotations

import math
import resource
import time
from collections.abc import Callable

import numpy as np

from ..cluster import (
    DEFAULT_KERNEL_CACHE,
    Cancelled,
    as_finished,
    connect,
    driver_variant,
    prepare_worker,
)
from ..config import FitConfig
from ..solvers import Problem, Result, run_schedule

#: |u| of the centre the other starts spread around (sigmoid(2) = 0.88 of a parameter's range).
CENTER_LIMIT = 2.0
#: Offset of the common loss's seed from the fit's seed (apart from the phases' seed + k).
COMMON_SEED_OFFSET = 0x5EED


def start_points(problem: Problem, start: dict, k: int, spread: float, seed: int) -> np.ndarray:
    """`k` unconstrained starting vectors (rows): the configured start, then `k - 1` spread
    around it (see the module's docstring)."""
    from scipy.stats import norm, qmc

    u0 = np.asarray(problem.unconstrained(start), np.float64)
    spread_mask = np.zeros(u0.size, bool)
    i = 0
    for f in problem.free:
        spread_mask[i : i + f.size] = not f.shape  # textures stay as configured
        i += f.size
    points = np.repeat(u0[None], k, axis=0)
    d = int(spread_mask.sum())
    if k > 1 and d:
        draws = qmc.LatinHypercube(d=d, rng=seed).random(k - 1)
        centre = np.clip(u0[spread_mask], -CENTER_LIMIT, CENTER_LIMIT)
        points[1:, spread_mask] = centre + spread * norm.ppf(draws)
    return points.astype(np.float32)


def common_loss(problem: Problem, u, spp: int, seed: int) -> float:
    """The loss at `u` at full resolution and `spp`, with the caller's seed (shared by starts)."""
    import jax.numpy as jnp

    from ..solvers.problem import jax_seed, residuals

    residual = residuals(problem, problem.render_fn("reverse", spp, 1), 1)
    r = residual(jnp.asarray(u, jnp.float32), jax_seed(seed))
    return float(0.5 * jnp.dot(r, r))


def fit_from(
    cfg: FitConfig, holdout: int | None, u: np.ndarray, variant: str | None, cache: str
) -> dict:
    """In a worker: `cfg`'s schedule from the unconstrained `u`, and the common loss there."""
    from .prepare import prepare

    prepare_worker(1, variant, cache)
    began = time.perf_counter()
    prepared = prepare(cfg, holdout, trace=False)
    problem = prepared.problem
    values = problem.values(u)
    start = {f.key: values[f.key] for f in problem.free}
    result = run_schedule(problem, start, prepared.phases, cfg.seed, None, cfg.uncertainty_spp)
    loss = common_loss(problem, result.u, cfg.starts_spp, cfg.seed + COMMON_SEED_OFFSET)
    return {
        "result": result,
        "start": start,
        "loss": loss,
        "wall_time_s": time.perf_counter() - began,
        "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def _small(values: dict) -> dict:
    """Values of at most 3 components (textures left out of the spread table)."""
    return {k: v for k, v in values.items() if np.size(v) <= 3}


def run_starts(
    cfg: FitConfig,
    prepared,
    holdout: int | None,
    on_start: Callable[[int, dict], None] | None = None,
    address: str | None = None,
) -> tuple[Result, list[dict], dict]:
    """The best of `cfg.starts` fits (by the common loss), the spread (per start its start and
    fitted values, common loss, the fit's own final loss, wall time and worker memory, or its
    one-line error) and the best one's start values. `on_start(k, row)` as each start ends. A
    failed start is reported and the others go on; Ctrl-C cancels the starts and raises
    `Cancelled`."""
    points = start_points(prepared.problem, prepared.start, cfg.starts, cfg.start_spread, cfg.seed)
    with connect(address):  # before Ray's import: its settings are read then
        import ray

        task = ray.remote(max_retries=0)(fit_from)
        refs = {
            task.remote(cfg, holdout, u, driver_variant(), DEFAULT_KERNEL_CACHE): k
            for k, u in enumerate(points)
        }
        outcomes: dict[int, dict] = {}
        failed: dict[int, dict] = {}
        pending = list(refs)
        try:
            for ref, outcome, error in as_finished(pending):
                k = refs[ref]
                if error is None:
                    outcomes[k] = outcome
                    row = _row(k, outcome)
                else:  # a worker died or the fit raised
                    failed[k] = _failed_row(k, prepared.problem.values(points[k]), error)
                    row = failed[k]
                if on_start:
                    on_start(k, row)
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise Cancelled(f"cancelled {len(pending)} of {cfg.starts} starts") from None
    if not outcomes:
        raise RuntimeError(
            f"every one of the {cfg.starts} starts failed; the first: "
            + next(iter(failed.values()))["error"]
        )
    rows = [_row(k, outcomes[k]) if k in outcomes else failed[k] for k in range(cfg.starts)]

    def loss(k: int) -> float:
        value = rows[k]["loss"]
        return value if value is not None and math.isfinite(value) else math.inf

    best = min(outcomes, key=loss)
    for row in rows:
        row["best"] = row["start"] == best
    return outcomes[best]["result"], rows, outcomes[best]["start"]


def _failed_row(k: int, start: dict, error: str) -> dict:
    """A start whose fit failed: its start values and the error, no result."""
    return {
        "start": k,
        "start_values": _small(start),
        "values": {},
        "loss": None,
        "fit_loss": None,
        "outcomes": ["failed"],
        "wall_time_s": 0.0,
        "max_rss_mb": None,
        "error": error,
    }


def _row(k: int, outcome: dict) -> dict:
    result: Result = outcome["result"]
    return {
        "start": k,
        "start_values": _small(outcome["start"]),
        "values": _small(result.values),
        "loss": outcome["loss"],
        "fit_loss": result.loss,
        "outcomes": [r.as_dict()["outcome"] for r in result.reports],
        "wall_time_s": outcome["wall_time_s"],
        "max_rss_mb": outcome["max_rss_mb"],
    }
