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
) -> Table:
    """Fit each synthetic case back from the common start with the default schedule (see
    `fit.recovery`); each outcome is saved to `results` (JSON, rewritten atomically after
    every case) and a case already there (same size, schedule and start) is not fitted again,
    so a stopped sweep resumes (`replace`: start again). The calibration table: each
    parameter's error and error/sigma."""
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
    advance = ticker(progress, "bench: recovery", len(cases))
    outcomes = []
    for case in cases:
        if case.name in done:
            outcome = recovery.Outcome.from_dict(case, done[case.name])
        else:
            outcome = recovery.recover(case, None, width, height)
            done[case.name] = outcome.as_dict()
            save(results, setting, "cases", done)
        outcomes.append(outcome)
        advance()
    passed = sum(o.passed() for o in outcomes)
    errors = [s for o in outcomes for k in recovery.KEYS for s in np.ravel(o.sigmas[k])]
    covered = sum(s <= recovery.MAX_SIGMAS for s in errors)
    return Table(
        title=f"Recovery over the range: {len(cases)} synthetic cases, 3 views of {width}x{height}",
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
            f"{passed} of {len(outcomes)} cases within every target (alpha 5 % relative, ior "
            "0.03, pigment 0.02) and 3 sd; "
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
