"""A Gauss-Newton phase and a schedule resumed where they stopped end as the whole run does."""

from __future__ import annotations

import numpy as np
import pytest
from sphere_problems import _gn, check, keep_offered

from fit.solvers import Phase, run_schedule


def test_gauss_newton_converges_and_resumes(larger):
    """The stochastic Gauss-Newton phase from a start off in every parameter lands within the
    tolerances in 24 steps of 16 spp on the 96x72 sphere (seeds 0-3: alpha within 9 %, pigment
    0.002; on the 48x36 one, whose highlight spans a few pixels, alpha ended -47 to -80 % for
    three seeds of four); stopped after step 16 (within the averaged tail) and resumed from its
    offered state (the curvature in it), it ends where the uninterrupted run does (to float
    rounding), with the same tail of gradients."""
    problem = larger
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.12, "glaze.ior": 1.4}
    u0 = problem.unconstrained(start)
    saved = {}
    whole = _gn(problem, u0, 24, offer=keep_offered(16, saved))
    check(whole.values)
    assert whole.reports[0].rejected == 0 and len(whole.history) == 24
    resumed = _gn(problem, u0, 24, resume=saved)
    np.testing.assert_allclose(resumed.u, whole.u, rtol=1e-4, atol=1e-5)
    for a, b in zip(resumed.tail_gradients, whole.tail_gradients, strict=True):
        assert a.shape == b.shape == (12, len(u0))
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)


def test_a_resumed_schedule_shows_its_finished_phases(problem, tmp_path):
    """Resumed after its first phase, a schedule reports that phase finished first (the
    progress bars of finished phases showed 0/N) and counts the work saved before it."""
    from fit.solvers import Checkpoint

    phases = (
        Phase(solver="adam", steps=2, spp=2, lr=0.1),
        Phase(solver="adam", steps=3, spp=2, lr=0.1),
    )
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}

    def stop_in_second(k, step, loss):
        if k == 1 and step == 1:
            raise KeyboardInterrupt

    checkpoint = Checkpoint(tmp_path / "checkpoint.npz", interval=1e9)
    with pytest.raises(KeyboardInterrupt):
        run_schedule(problem, start, phases, 0, stop_in_second, 2, checkpoint)
    worked = checkpoint.elapsed()
    calls = []
    again = Checkpoint(tmp_path / "checkpoint.npz", interval=1e9)  # a new process's
    run_schedule(problem, start, phases, 0, lambda *a: calls.append(a[:2]), 2, again, resume=True)
    assert calls[0] == (0, 2) and (1, 3) in calls
    # the resumed run's clock starts from the saved work (the summary's wall time: the run's)
    assert 0 < again.elapsed_before <= worked


def test_a_schedule_stopped_after_its_last_phase_resumes_with_its_loss_and_tail(
    problem, tmp_path, monkeypatch
):
    """Stopped after the last phase's end (in the uncertainty, or writing the run folder), a
    resumed fit ran no phase and reported the loss NaN and an sd without the averaged tail's
    noise (smaller than the uninterrupted run's). Its end's checkpoint now keeps both."""
    import fit.solvers.schedule as schedule_module
    from fit.solvers import Checkpoint

    phases = (Phase(solver="gn", steps=8, spp=2, jacobian_spp=4, refresh=4, average=1.0),)
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    whole = run_schedule(problem, start, phases, 0, None, 2)
    real = schedule_module.uncertainty

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(schedule_module, "uncertainty", stop)
    checkpoint = Checkpoint(tmp_path / "checkpoint.npz", interval=1e9)
    with pytest.raises(KeyboardInterrupt):
        run_schedule(problem, start, phases, 0, None, 2, checkpoint)
    monkeypatch.setattr(schedule_module, "uncertainty", real)
    again = Checkpoint(tmp_path / "checkpoint.npz", interval=1e9)
    resumed = run_schedule(problem, start, phases, 0, None, 2, again, resume=True)
    assert whole.tail_variance is not None and whole.tail_gradients is not None
    # float32 rounding and a replay's flipped samples against the recording's: 4e-5 seen
    assert resumed.loss == pytest.approx(whole.loss, rel=2e-4)
    # Two runs of one schedule differ by the rounding of Dr.Jit's threaded sums (on 2 cores:
    # 1.7e-4 in the iterates' scatter) and by a frozen Jacobian's replay against its recording
    # (now and then a sample flipped: 3e-4 of the largest gradient); a lost tail would be None
    # or its noise left out.
    np.testing.assert_allclose(resumed.tail_variance, whole.tail_variance, rtol=2e-3)
    for a, b in zip(resumed.tail_gradients, whole.tail_gradients, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-3 * np.abs(b).max())
    for key in whole.std:
        np.testing.assert_allclose(resumed.std[key], whole.std[key], rtol=1e-3)


def test_a_phase_that_settles_resumes_to_the_same_end(larger):
    """A `gn` phase with a window, stopped after its fifth step (before its first check) and
    resumed from the offered state (its iterates in it), settles at the same step as the
    uninterrupted run and ends at the same answer."""
    problem = larger
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.12, "glaze.ior": 1.4}
    u0 = problem.unconstrained(start)
    saved = {}
    whole = _gn(problem, u0, 60, offer=keep_offered(5, saved), window=8)
    assert whole.reports[0].outcome == "converged" and 8 < whole.reports[0].steps < 60
    resumed = _gn(problem, u0, 60, resume=saved, window=8)
    assert resumed.reports[0].steps == whole.reports[0].steps
    np.testing.assert_allclose(resumed.u, whole.u, rtol=1e-4, atol=1e-5)
