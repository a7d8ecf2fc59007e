"""Where a fit's time goes: the default schedule on a recovery case, profiled (Dr.Jit's kernel
history and the wall time inside each kind of renderer call)."""

from __future__ import annotations

import time

from .common import Table, machine, short
from .problems import recovery_problem


def profile_table(width: int = 160, shape: str = "sphere") -> Table:
    """The default schedule on a recovery case (three views of `width` x 3/4 width), after an
    untimed warm-up that compiles every kernel, profiled: Dr.Jit's kernel history (kernel
    execution, IR generation, compilation) and the wall time inside each kind of renderer call
    (primal, reverse, Jacobian); what is left is JAX, the solvers and Python around them."""
    import drjit as dr

    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE, run_schedule

    height = width * 3 // 4
    capture = recovery.capture(recovery.Case(shape), width, height)
    # The warm-up runs on the timed fit's own scenes, two steps a phase: every frozen function
    # records at its first call and again at its second. Kernels of scenes loaded after others
    # in one process are compiled anew (Dr.Jit's kernel history: no memory or disk cache hit),
    # so a warm-up on other scenes left 3.9-5.7 s of LLVM inside the timed fit at 160x120.
    problem = recovery_problem(capture)
    run_schedule(problem, recovery.START, short(DEFAULT_SCHEDULE, 2), 0)
    inside = {"primal": [0, 0.0], "reverse": [0, 0.0], "jacobian": [0, 0.0]}
    for downscale in (1, 2):
        renderer = problem.renderer(downscale)
        for kind, name in (("primal", "render"), ("reverse", "vjp"), ("jacobian", "jacobian")):
            setattr(renderer, name, _timed_call(getattr(renderer, name), inside[kind]))
    dr.kernel_history_clear()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
        began = time.perf_counter()
        run_schedule(problem, recovery.START, DEFAULT_SCHEDULE, 0)
        wall = time.perf_counter() - began
        history = dr.kernel_history()
    execution = sum(k.get("execution_time", 0.0) for k in history) / 1000
    codegen = sum(k.get("codegen_time", 0.0) for k in history) / 1000
    backend = sum(k.get("backend_time", 0.0) for k in history) / 1000
    renderer_wall = sum(t for _, t in inside.values())
    kernels = sum(1 for k in history if k.get("type") == dr.KernelType.JIT)
    rows = [["whole fit (default schedule, uncertainty included)", f"{wall:.2f}", "100 %", ""]]

    def row(label, seconds, note=""):
        rows.append([label, f"{seconds:.2f}", f"{100 * seconds / wall:.1f} %", note])

    for kind, (calls, seconds) in inside.items():
        row(f"inside renderer calls: {kind}", seconds, f"{calls} calls")
    row("  of which Dr.Jit kernels executing", execution, f"{kernels} kernel launches")
    row("  of which kernel IR generation (tracing)", codegen)
    row("  of which compilation (LLVM)", backend, "0 when every kernel is cached")
    row(
        "  the rest inside (Python plugins traced, replays, host copies)",
        renderer_wall - execution - codegen - backend,
    )
    row("outside renderer calls (JAX, solvers, Python)", wall - renderer_wall)
    row("outside Mitsuba's kernels (all but execution)", wall - execution)
    return Table(
        title=f"Where a fit's time goes: default schedule, {shape}, 3 views of {width}x{height}",
        columns=["part", "seconds", "share", "note"],
        rows=rows,
        notes=[
            "Dr.Jit's kernel history (execution, IR generation and compile times) and wall "
            "time around each renderer call, after an untimed two-step-per-phase warm-up on "
            "the same scenes (every frozen function recorded)",
            machine(),
        ],
    )


def _timed_call(call, total: list):
    """`call`, adding its count and wall time to `total` ([calls, seconds])."""

    def timed(*args, **kwargs):
        began = time.perf_counter()
        try:
            return call(*args, **kwargs)
        finally:
            total[0] += 1
            total[1] += time.perf_counter() - began

    return timed
