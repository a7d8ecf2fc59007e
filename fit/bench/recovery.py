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
    # each miss: what its target allows at all (two Jacobian renders at the truth; saved, so a
    # resumed sweep does not render them again)
    limits = []
    for outcome in outcomes:
        if outcome.passed():
            continue
        entry = done[outcome.case.name]
        if "limit" not in entry:
            limit = recovery.data_limit(outcome.case, width, height)
            entry["limit"] = {k: recovery.strict(v) for k, v in limit.items()}
            save(results, setting, "cases", done)
        sd = entry["limit"]["glaze.roughness"]
        alpha = "undetermined" if sd is None else f"{100 * sd / outcome.case.roughness:.1f} %"
        limits.append(f"{outcome.case.name}: {alpha}")
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
            "within targets and 3 sd",
        ],
        rows=recovery.calibration_rows(outcomes),
        notes=[
            f"{passed} of {len(outcomes)} cases within every target (alpha 5 % relative, ior "
            "0.03, pigment 0.02) and 3 sd; "
            f"{covered} of {len(errors)} parameter errors within 3 reported sd",
            f"each case: the truth rendered at {recovery.TARGET_SPP} spp, fitted from "
            f"{recovery.START} with the default schedule ({schedule}); ✗ marks a miss",
            *(
                [
                    "what the target's own noise allows alpha in each miss (its sd at the truth "
                    f"from two {recovery.LIMIT_SPP}-spp Jacobians, no fit): " + "; ".join(limits)
                ]
                if limits
                else []
            ),
            machine(),
        ],
    )
