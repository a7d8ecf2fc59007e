"""Recovery over the parameter range: each synthetic case of `fit.recovery` fitted back with the
default schedule, resumably; the calibration table (errors against the reported sd)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .common import Table, machine, resumed, save, schedule_key, ticker


def recovery_table(
    cases: list,
    width: int,
    height: int,
    results: Path,
    progress=None,
    replace: bool = False,
    seeds: int = 1,
) -> Table:
    """Fit each synthetic case back from the common start with the default schedule (see
    `fit.recovery`), with fit seeds 0 to `seeds - 1` against one clean target per case; each
    outcome is saved to `results` (JSON, rewritten atomically after every fit) and one already
    there (same size, schedule and start) is not fitted again, so a stopped sweep resumes, and a
    sweep of one seed goes on to more (`replace`: start again). The calibration table: each
    fit's errors and error/sigma."""
    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE

    schedule = " + ".join(
        f"{p.solver} {p.steps} x {p.spp} spp 1/{p.downscale}" for p in DEFAULT_SCHEDULE
    )
    setting = {
        "size": [width, height],
        "schedule": schedule,
        "phases": schedule_key(DEFAULT_SCHEDULE),
        "start": recovery.START,
        "targets": f"alpha within {recovery.ALLOWANCE:g} by at most {recovery.MAX_TARGET_SPP} spp",
    }
    done = resumed(
        results,
        setting,
        "cases",
        "a sweep of another size, schedule, start or fitting code (its constants)",
        replace,
        ("values", "std", "seconds"),
    )
    advance = ticker(progress, "bench: recovery", len(cases) * seeds)
    outcomes = []
    for case in cases:
        clean = None  # rendered once for the case's seeds
        for seed in range(seeds):
            key = recovery.fit_label(case, seed)
            if key in done:
                outcome = recovery.Outcome.from_dict(case, done[key])
            else:
                if clean is None and seeds > 1:
                    clean = recovery.clean_target(case, width, height)
                outcome = recovery.recover(case, None, width, height, seed=seed, clean=clean)
                done[key] = outcome.as_dict()
                save(results, setting, "cases", done)
            outcomes.append(outcome)
            advance()
    passed = sum(o.passed() for o in outcomes)
    errors = [s for o in outcomes for k in recovery.KEYS for s in np.ravel(o.sigmas[k])]
    covered = sum(s <= recovery.MAX_SIGMAS for s in errors)
    return Table(
        title=f"Recovery over the range: {len(cases)} synthetic cases"
        + (f", fit seeds 0-{seeds - 1}" if seeds > 1 else "")
        + f", 3 views of {width}x{height}",
        columns=[
            "case",
            "alpha error (error / sd)",
            "ior error",
            "pigment, worst channel",
            "wall s",
            "target spp (allows alpha)",
            "within targets and 3 sd",
        ],
        rows=recovery.calibration_rows(outcomes),
        notes=[
            f"{passed} of {len(outcomes)} {'fits' if seeds > 1 else 'cases'} within every "
            "target (alpha 5 % relative, ior 0.03, pigment 0.02) and 3 sd; "
            f"{covered} of {len(errors)} parameter errors within 3 reported sd",
            f"each case: the truth rendered at {recovery.TARGET_SPP} spp or more, until its "
            f"noise allows alpha {100 * recovery.ALLOWANCE:.1f} % (at most "
            f"{recovery.MAX_TARGET_SPP}), fitted from "
            f"{recovery.START} with the default schedule ({schedule}); ✗ marks a miss",
            "what a target allows alpha: its optimum's sd over such targets at the truth "
            f"(`data_limit` from two {recovery.TARGET_LIMIT_SPP}-spp Jacobians, no fit)",
            machine(),
        ],
    )
