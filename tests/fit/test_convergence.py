"""Phases that end when they are done (`gn`'s `window`), quality presets, and the fit's time
recorded part by part."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from sphere_problems import _gn, keep_offered

from captures.errors import InputError
from fit import timing
from fit.solvers import DEFAULT_SCHEDULE, Phase
from fit.solvers.base import Outcome
from fit.solvers.gn import _averaged, burn_in, settled
from fit.solvers.schedule import (
    DRAFT_MIN_SIDE,
    DRAFT_PRECISION,
    DRAFT_SAMPLES,
    QUALITIES,
    at_quality,
)


def _wandering(rng, coordinates: int, window: int, drift: float = 0.0) -> np.ndarray:
    """A `gn` phase's iterates at its optimum (an AR(1): half the way back each step, plus
    noise of sd 1 / sqrt(3) at rest), plus a steady `drift` per step in units of that sd."""
    u, rows = np.zeros(coordinates), []
    for t in range(window + 21):
        u = 0.5 * u + 0.5 * rng.normal(size=coordinates)
        rows.append(u + drift * t / np.sqrt(3.0))
    return np.asarray(rows[-(window + 1) :])


@pytest.mark.parametrize("coordinates", [1, 6, 23])
def test_settled_passes_noise_about_half_the_time_and_drift_rarely(coordinates):
    """At the optimum a window of 16 passes about half its checks whatever the number of
    coordinates (measured 0.42-0.47); a drift of a fifth of the noise's sd a step rarely
    passes, a tenth of it in at most a third of the checks."""
    rng = np.random.default_rng(0)

    def rate(drift):
        return np.mean([settled(list(_wandering(rng, coordinates, 16, drift))) for _ in range(600)])

    assert 0.3 <= rate(0.0) <= 0.6
    assert rate(0.1) <= 0.33
    assert rate(0.2) <= 0.1


def test_settled_refuses_rejected_steps_and_short_windows():
    """A NaN (a rejected step) in the window, or fewer than three rows: not settled; a
    coordinate that never moves (no signal) is settled."""
    rows = _wandering(np.random.default_rng(1), 2, 16)
    rows[:, 1] = 0.0
    assert settled(list(rows), tolerance=10.0)
    rows[3, 0] = np.nan
    assert not settled(list(rows), tolerance=10.0)
    assert not settled(list(rows[-2:]), tolerance=10.0)


def _relaxing(rng, steps: int, coordinates: int, start: float) -> np.ndarray:
    """A `gn` phase's iterates that start `start` from the optimum in the first coordinate and
    relax 10 % of the way a step, with white noise of sd 1 (the averaged phase's iterates on
    the torus at alpha 0.01: from +49 % in log, 6.3 % noise, lag-1 autocorrelation -0.09 at
    rest, about 16 steps to relax)."""
    u = np.zeros(coordinates)
    u[0] = start
    rows = []
    for _ in range(steps):
        rows.append(u + rng.normal(size=coordinates))
        u = 0.9 * u
    return np.asarray(rows)


@pytest.mark.parametrize("coordinates", [5, 20])
def test_burn_in_leaves_out_a_relaxation_and_rarely_noise(coordinates):
    """Iterates at rest: some first steps left out in at most 3 % of 300 phases (the level is
    1 %); relaxing from 8 noise sds away (the torus's alpha 0.01 started 6.3 away: over its 32
    steps +15.5 % averaged from the start, +2.6 % from half-way), the first steps are left out in
    most phases (measured 95 % with 5 coordinates, 75 % with 20), and then the average is
    closer than the plain one."""
    rng = np.random.default_rng(0)
    alarms = [burn_in(list(_relaxing(rng, 32, coordinates, 0.0)), 0.5) for _ in range(300)]
    assert np.mean(np.asarray(alarms) > 0) <= 0.03
    hits, closer = 0, 0
    for _ in range(100):
        rows = _relaxing(rng, 32, coordinates, 8.0)
        d = burn_in(list(rows), 0.5)
        hits += d >= 4
        closer += d >= 4 and abs(rows[d:, 0].mean()) < abs(rows[:, 0].mean())
    assert hits >= 60 and closer >= 0.9 * hits, (hits, closer)


def test_burn_in_keeps_short_or_half_averaged_phases_whole():
    """Fewer than 12 iterates, a rejected step, or a phase that averages half its steps (the
    relaxing one): nothing is left out."""
    rng = np.random.default_rng(1)
    rows = _relaxing(rng, 32, 3, 100.0)
    assert burn_in(list(rows[:11]), 0.5) == 0
    assert _averaged(list(rows), 0.5, 0.5) == 16
    assert _averaged(list(rows), 1.0, 0.5) < 32
    rows[5, 1] = np.nan
    assert burn_in(list(rows), 0.5) == 0


def _linear(problem, monkeypatch, optimum):
    from test_solve import _linear_images

    _linear_images(problem, monkeypatch, optimum)


def test_a_windowed_phase_ends_when_settled_at_the_optimum(problem, monkeypatch):
    """On an exact linear image from a far start, `gn` with a window ends `converged` before
    its step limit, at the optimum (it does not stop while it still moves), and says after how
    many steps; its result averages the last half of the steps it took."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _linear(problem, monkeypatch, truth)
    start = {"glaze.pigment": [0.4, 0.4, 0.4], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    result = _gn(problem, problem.unconstrained(start), 200, window=8, average=0.5)
    report = result.reports[0]
    assert report.outcome == Outcome.CONVERGED
    assert 8 <= report.steps < 200 and len(result.history) == report.steps
    assert f"settled after {report.steps} of 200 steps" in report.message
    assert result.values["glaze.roughness"] == pytest.approx(0.05, rel=1e-3)
    np.testing.assert_allclose(result.values["glaze.pigment"], truth["glaze.pigment"], atol=1e-4)
    assert len(result.tail_gradients[0]) == round(0.5 * report.steps)
    without = _gn(problem, problem.unconstrained(start), 30, average=0.5)
    assert without.reports[0].outcome == Outcome.STEP_LIMIT and without.reports[0].steps == 30


@pytest.mark.parametrize("burn_in_min", [12, 10**6])
def test_an_averaged_phase_leaves_out_its_relaxation(problem, monkeypatch, burn_in_min):
    """On an exact linear image from a far start, a phase that averages all its steps (as the
    default's last one does) leaves the first ones, while it still relaxed, out of its answer:
    it is the optimum, and the phase says so (measured 0.0505 for 0.05). Never left out (the
    check off), the mean of every step stays between the start and the optimum (0.0624)."""
    import fit.solvers.gn as gn

    monkeypatch.setattr(gn, "BURN_IN_MIN", burn_in_min)
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _linear(problem, monkeypatch, truth)
    start = {"glaze.pigment": [0.4, 0.4, 0.4], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    result = _gn(problem, problem.unconstrained(start), 24, average=1.0, eta=0.3)
    alpha, report = result.values["glaze.roughness"], result.reports[0]
    if burn_in_min > 24:
        assert 0.055 < alpha < 0.2 and "still relaxing" not in report.message, alpha
        return
    assert alpha == pytest.approx(0.05, rel=0.02)
    assert "averaged its last" in report.message and "of 24 steps" in report.message
    assert 12 <= len(result.tail_gradients[0]) < 24


def test_quality_presets_change_every_phase():
    """draft: half the steps, step limits and a relaxing phase's fewest steps (rounded up), the
    full-resolution phases at half resolution, every phase's samples but the last's halved, a
    precise phase averaged to `DRAFT_PRECISION` at least; best: twice the steps and limits;
    default: the phases as they are; their other options kept."""
    assert at_quality(DEFAULT_SCHEDULE) == DEFAULT_SCHEDULE
    draft = at_quality(DEFAULT_SCHEDULE, "draft")
    best = at_quality(DEFAULT_SCHEDULE, "best")
    halved = {"max_steps", "precision", "relaxed_min", "relaxed_min_determined", *DRAFT_SAMPLES}
    last = len(DEFAULT_SCHEDULE) - 1
    for i, (phase, d, b) in enumerate(zip(DEFAULT_SCHEDULE, draft, best, strict=True)):
        assert d.steps == -(-phase.steps // 2) and b.steps == 2 * phase.steps
        samples = {k: v for k, v in phase.model_dump().items() if k in DRAFT_SAMPLES and v}
        drafted = {k: v for k, v in d.model_dump().items() if k in DRAFT_SAMPLES and v}
        assert drafted == {k: v if i == last else v // 2 for k, v in samples.items()}
        assert {k: v for k, v in b.model_dump().items() if k in samples} == samples
        assert d.downscale == (2 if phase.downscale == 1 else phase.downscale)
        assert b.downscale == phase.downscale
        limit = getattr(phase.options, "max_steps", None)
        if limit:
            assert d.options.max_steps == -(-limit // 2) and b.options.max_steps == 2 * limit
        precision = getattr(phase.options, "precision", None)
        if precision:
            assert d.options.precision == max(precision, DRAFT_PRECISION)
            assert b.options.precision == precision
        if getattr(phase.options, "relaxed", False):
            assert (d.options.relaxed_min, d.options.relaxed_min_determined) == (15, 10)
            assert (b.options.relaxed_min, b.options.relaxed_min_determined) == (30, 20)
        same = phase.options.model_dump(exclude=halved)
        for changed in (d, b):
            assert changed.options.model_dump(exclude=halved) == same
    assert any(getattr(p.options, "max_steps", None) for p in DEFAULT_SCHEDULE)  # checked above
    assert any(getattr(p.options, "precision", 0) for p in DEFAULT_SCHEDULE)
    assert any(getattr(p.options, "relaxed", False) for p in DEFAULT_SCHEDULE)
    assert draft[1].spp == 8 and draft[1].options.spp_limit == 32 and draft[-1].spp == 64
    loose = Phase(solver="gn", steps=8, spp=4, precision=0.4, max_steps=16)
    assert at_quality((loose,), "draft")[0].options.precision == 0.4  # it asks less already
    odd = (Phase(solver="adam", steps=1, spp=4, downscale=3, lr=0.2),)
    assert at_quality(odd, "draft")[0].steps == 1 and at_quality(odd, "draft")[0].downscale == 3
    with pytest.raises(ValueError, match="choose one of draft, default, best"):
        at_quality(DEFAULT_SCHEDULE, "fast")
    assert QUALITIES == ("draft", "default", "best")


@pytest.mark.parametrize(
    "side, halved", [(None, True), (2 * DRAFT_MIN_SIDE, True), (2 * DRAFT_MIN_SIDE - 1, False)]
)
def test_draft_halves_resolution_where_views_keep_enough_pixels(side, halved):
    """A draft renders a full-resolution phase at half resolution only where the views keep
    `DRAFT_MIN_SIDE` pixels a side (the views' size unknown: it halves); its steps are halved
    either way, and a phase at its own lower resolution keeps it."""
    phases = (*DEFAULT_SCHEDULE, Phase(solver="adam", steps=4, spp=4, downscale=3, lr=0.1))
    draft = at_quality(phases, "draft", side)
    for phase, d in zip(phases, draft, strict=True):
        expected = 2 if phase.downscale == 1 and halved else phase.downscale
        assert d.downscale == expected and d.steps == -(-phase.steps // 2)
    assert at_quality(phases, "best", side) == at_quality(phases, "best")


def test_relaxed_minima_are_options_and_checked():
    """A relaxing phase's fewest steps are options (30 and 20 unless given); the determined one
    above the other is refused, naming it and the fix."""
    from fit.solvers.gn import RELAXED_MIN, RELAXED_MIN_DETERMINED

    phase = Phase(solver="gn", steps=56, spp=16, relaxed=True)
    assert (phase.options.relaxed_min, phase.options.relaxed_min_determined) == (
        RELAXED_MIN,
        RELAXED_MIN_DETERMINED,
    )
    with pytest.raises(Exception, match="= 20 is above relaxed_min = 10; lower it"):
        Phase(solver="gn", steps=56, spp=16, relaxed=True, relaxed_min=10)


def test_fit_quality_applies_to_a_configs_own_phases(tmp_path, shared_data):
    """`fit.quality` in a config changes its own `[[fit.phases]]` (and the default schedule's),
    and an unknown one is refused naming the key."""
    from test_fitconfig import PHASES, ROOT

    from fit.config import load_fit_config

    text = (ROOT / "configs" / "peer-sphere.toml").read_text()
    text = text.replace('"../../shared/data', f'"{shared_data}')
    path = tmp_path / "fit.toml"
    path.write_text(text.replace("seed = 0", 'seed = 0\nquality = "best"') + PHASES)
    assert [p.steps for p in load_fit_config(path).phases] == [200, 10]
    path.write_text(text.replace("seed = 0", 'seed = 0\nquality = "draft"'))
    assert load_fit_config(path).phases == list(at_quality(DEFAULT_SCHEDULE, "draft"))
    path.write_text(text.replace("seed = 0", 'seed = 0\nquality = "fast"'))
    with pytest.raises(InputError, match=r"fit\.quality"):
        load_fit_config(path)


def test_a_layered_materials_draft_keeps_its_samples(tmp_path, shared_data):
    """A draft of the cup (layers sharing each pixel's samples by Russian roulette) keeps every
    phase's samples and halves its steps; a draft of the one-layer sphere halves the samples of
    every phase but the last (the schedule alone knows no material: it halves)."""
    from test_fitconfig import ROOT

    from fit.config import load_fit_config

    def samples(phase):
        return {k: v for k, v in phase.model_dump().items() if k in DRAFT_SAMPLES}

    cup = load_fit_config(ROOT / "configs" / "cup-fit.toml")
    cup = dataclasses.replace(cup, settings=cup.settings.model_copy(update={"quality": "draft"}))
    assert cup.layered
    for phase, d in zip(cup.settings.phases, cup.phases_for(56), strict=True):
        assert samples(d) == samples(phase) and d.steps == -(-phase.steps // 2)
    text = (ROOT / "configs" / "peer-sphere.toml").read_text()
    path = tmp_path / "fit.toml"
    text = text.replace('"../../shared/data', f'"{shared_data}')
    path.write_text(text.replace("seed = 0", 'seed = 0\nquality = "draft"'))
    sphere = load_fit_config(path)
    assert not sphere.layered
    assert [p.spp for p in sphere.phases_for(120)] == [4, 8, 64]
    assert at_quality(DEFAULT_SCHEDULE, "draft") == at_quality(DEFAULT_SCHEDULE, "draft", 120)


def test_timing_records_parts_only_inside_a_recording():
    """Parts add up inside a recording (raising ones too) and cost nothing outside."""
    timing.add("outside", 1.0)
    with timing.recording() as parts:
        timing.add("a", 1.0)
        timing.add("a", 0.5)
        with pytest.raises(RuntimeError), timing.timed("b"):
            raise RuntimeError
        assert timing.recorded() == parts
    assert parts["a"] == 1.5 and parts["b"] >= 0.0 and "outside" not in parts
    assert timing.recorded() == {}


def test_the_summary_times_the_fit_part_by_part(tmp_path):
    """`layerfit fit` writes where its time went into `summary.json`: start-up, the capture,
    each phase's first step (its renders recorded and compiled) and the others, the
    uncertainty and the report; the phases' parts add up to their reported seconds. With
    `--quality` the phases are the preset's, and a stop's resume command repeats it."""
    from test_fit_cli import CONFIG, small_capture

    from fit.commands.fit import fit, resume_command

    small_capture(tmp_path / "cap", views=2, size=(32, 24))
    (tmp_path / "fit.toml").write_text(
        CONFIG + '[[fit.phases]]\nsolver = "adam"\nsteps = 4\nspp = 4\nlr = 0.1\n'
        '[[fit.phases]]\nsolver = "gn"\nsteps = 3\nspp = 8\njacobian_spp = 8\n'
    )
    summary, out = fit(tmp_path / "fit.toml", tmp_path / "run", quality="draft")
    timings = json.loads((out / "summary.json").read_text())["timings_s"]
    phases = summary["outcomes"]
    assert [(o["solver"], o["steps"]) for o in phases] == [("adam", 2), ("gn", 2)]
    # 32x24 views: half resolution would leave 12 pixels a side, under `DRAFT_MIN_SIDE`
    assert [p["downscale"] for p in summary["phases"]] == [1, 1]
    expected = ["start Mitsuba, Dr.Jit and the plugins", "read the capture, build the problem"]
    for k, o in enumerate(phases):
        expected += [f"phase {k + 1} ({o['solver']}): {p}" for p in ("first step", "other steps")]
    expected += ["uncertainty", "report: renders of the fitted views"]
    expected += ["report: figures, preset and files"]
    assert list(timings) == expected
    assert all(v >= 0 for v in timings.values())
    for k, o in enumerate(phases):
        mine = sum(v for key, v in timings.items() if key.startswith(f"phase {k + 1} "))
        assert mine == pytest.approx(o["seconds"], rel=1e-6)
    line = resume_command(tmp_path / "fit.toml", out, None, None, quality="draft")
    assert line.endswith("--resume --quality draft")
    with pytest.raises(InputError, match="--quality 'fast': choose one of draft, default, best"):
        fit(tmp_path / "fit.toml", tmp_path / "other", quality="fast")
    assert not (tmp_path / "other").exists()


def test_the_uncertainty_takes_the_last_phases_jacobians(problem, monkeypatch):
    """Where the last `gn` phase's two series of Jacobian renders hold at least half the
    uncertainty's samples each, the uncertainty renders nothing and gives what its own renders
    give: on exact linear images with a misfit no parameter explains, the same sd as with
    `uncertainty_spp` above what the phase holds (each series topped up by a render of the
    rest)."""
    from fit.solvers import run_schedule

    target, _ = problem.target(1)
    rng = np.random.default_rng(5)
    jac = rng.normal(size=(target.size, 5)).astype(np.float32) * 0.05
    misfit = 0.01 * rng.normal(size=target.size).astype(np.float32)
    x_ref = np.array([0.1, 0.22, 0.55, 0.1, 1.5], np.float32)
    calls = []

    def image(x):
        return target + misfit + jac @ (np.asarray(x, np.float32) - x_ref)

    class Linear:
        def jacobian(self, values, seed, spp):
            calls.append(spp)
            return image(values), jac

    import jax.numpy as jnp

    monkeypatch.setattr(
        problem,
        "render_fn",
        lambda *a, **k: (
            lambda x, seed: (
                jnp.asarray(target + misfit) + jnp.asarray(jac) @ (x - jnp.asarray(x_ref))
            )
        ),
    )
    monkeypatch.setattr(problem, "renderer", lambda downscale=1: Linear())
    start = {"glaze.pigment": [0.12, 0.2, 0.5], "glaze.roughness": 0.12, "glaze.ior": 1.45}
    phase = Phase(solver="gn", steps=4, spp=8, jacobian_spp=16, refresh=2, average=1.0)
    reused = run_schedule(problem, start, [phase], 0, uncertainty_spp=32)
    assert calls == [8] * 4  # two refreshes of two renders: none for the uncertainty
    calls.clear()
    rendered = run_schedule(problem, start, [phase], 0, uncertainty_spp=64)
    assert calls == [8] * 4 + [16] * 2  # each series holds 16 of the 32 asked
    for key, sd in rendered.std.items():
        np.testing.assert_allclose(reused.std[key], sd, rtol=1e-4)
        assert np.all(np.asarray(sd) > 0)


def test_quality_table_compares_whole_commands_with_the_loop(tmp_path, monkeypatch):
    """Each (object, preset, seed) command and each loop seed runs once (a rerun reads them
    back); the table gives median times, the loop's time over each sphere preset's, the median
    errors (colour worst channel, alpha relative, ior) and the errors within 3 sd; the second
    table the default's parts, cold and warm, with the untimed rest; the plot is written."""
    from fit.bench import quality

    ran = []
    seconds = {"draft": 10.0, "default": 20.0, "best": 40.0}

    def fake_command(config, preset, seed, cold=None):
        ran.append((str(config), preset, seed, cold is not None))
        scale = {"draft": 4.0, "default": 2.0, "best": 1.0}[preset]
        return {
            "seconds": seconds[preset] + seed + (5.0 if cold is not None else 0.0),
            "fit_seconds": seconds[preset] - 3.0,
            "errors": {
                "g.pigment": [0.001 * scale, -0.002 * scale, 0.0],
                "g.roughness": 0.001,
                "g.ior": -0.003 * scale,
                "gain.view": [0.5],
            },
            "truth": {"g.pigment": [0.1, 0.2, 0.3], "g.roughness": 0.05, "g.ior": 1.5},
            "error_over_std": {"g.pigment": [0.5, 1.0, 0.1], "g.ior": 4.0 if scale == 4 else 1.0},
            "timings": {
                "phase 1 (adam): first step": 1.0 + (2.0 if cold is not None else 0.0),
                "uncertainty": 2.0,
            },
            "steps": [100, 14, 8],
        }

    def fake_loop(config, seed):
        ran.append((str(config), "loop", seed, False))
        return {
            "seconds": 100.0 + seed,
            "errors": {"g.pigment": [0.01, 0.0, 0.0], "g.roughness": 0.002, "g.ior": 0.004},
            "truth": {"g.pigment": [0.1, 0.2, 0.3], "g.roughness": 0.05, "g.ior": 1.5},
        }

    monkeypatch.setattr(quality, "command_run", fake_command)
    monkeypatch.setattr(quality, "loop_run", fake_loop)
    cases = (("sphere", Path("s.toml")), ("torus", Path("t.toml")))
    presets, parts = quality.quality_table(
        3, tmp_path / "q.json", cases=cases, plot=tmp_path / "q.png"
    )
    assert len(ran) == 1 + 3 * (1 + 2 * 3) and sum(c for *_, c in ran) == 1
    assert (tmp_path / "q.png").stat().st_size > 10_000
    rows = {(r[0], r[1]): r for r in presets.rows}
    # sphere default: median 21 s, the loop's 101 s is 4.8x; colour 0.004, alpha 2 %, ior 0.006
    assert rows[("sphere", "default")][2:7] == ["21.0", "4.8x", "0.0040", "2.0 %", "0.0060"]
    assert rows[("sphere", "the tutorial loop")][2:7] == [
        "101.0",
        "1.0x",
        "0.0100",
        "4.0 %",
        "0.0040",
    ]
    assert rows[("torus", "default")][3] == "-"  # the loop runs on the sphere only
    assert rows[("sphere", "draft")][-1] == "9 of 12" and rows[("sphere", "best")][-1] == "12 of 12"
    table = {r[0]: r[1:] for r in parts.rows}
    assert table["phase 1 (adam): first step"] == ["3.00", "1.00"]
    assert table["whole command"] == ["25.00", "20.00"]
    assert table["interpreter, imports, exit (the rest)"] == ["20.00", "17.00"]
    quality.quality_table(3, tmp_path / "q.json", cases=cases)
    assert len(ran) == 22  # all read back


def test_draft_keeps_the_resolution_of_small_views(tmp_path):
    """A draft of views too small to halve keeps their resolution (and halves the steps); its
    summary lists the phases it ran, and its checkpoint identity matches them."""
    from test_fit_cli import CONFIG, small_capture

    from fit.commands.fit import fit

    small_capture(tmp_path / "cap", views=1, spp=16, size=(8, 6))
    (tmp_path / "fit.toml").write_text(
        CONFIG + '[[fit.phases]]\nsolver = "adam"\nsteps = 4\nspp = 4\nlr = 0.1\n'
    )
    summary, _ = fit(tmp_path / "fit.toml", tmp_path / "run", quality="draft")
    assert [(p["downscale"], p["steps"]) for p in summary["phases"]] == [(1, 2)]
    assert [o["steps"] for o in summary["outcomes"]] == [2]


def _noisy_linear(problem, monkeypatch, optimum, noise: float, calls: list):
    """`_linear` with each step's image carrying noise of sd `noise / sqrt(spp)` (its seed's),
    the samples of every step render recorded in `calls` as (image spp, reverse spp)."""
    import jax

    _linear(problem, monkeypatch, optimum)
    exact = problem.render_fn("reverse", 1, 1)

    def render_fn(mode, spp, downscale, grad_spp=None, **_):
        calls.append((spp, grad_spp))

        def render(x, seed):
            key = jax.random.PRNGKey(seed)
            image = exact(x, seed)
            return image + noise / np.sqrt(spp) * jax.random.normal(key, image.shape)

        return render

    monkeypatch.setattr(problem, "render_fn", render_fn)


@pytest.mark.parametrize("noise", [0.0, 40.0])
def test_a_phase_with_noisy_steps_raises_its_samples(problem, monkeypatch, noise):
    """With `spp_limit`, a `gn` phase whose steps wander more than `max_step_noise` of a value
    renders 4x the samples (image and reverse pass) from its next curvature refresh on, up to
    the limit, and says so; with quiet steps it keeps its samples. On an exact linear image
    with noise of sd 40 / sqrt(spp) per pixel, alpha's steps at 4 spp wander far more than 5 %
    of alpha (65 % at 16 spp, measured); without noise they only relax toward it from a start
    away from it, and relaxing is not noise (the raw steps' sd: 8.7 % of alpha)."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    calls = []
    _noisy_linear(problem, monkeypatch, truth, noise, calls)
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.3, "glaze.ior": 1.4}
    u0 = problem.unconstrained(start)
    # stricter than the default, so that a relaxation taken for noise would raise it (8.7 %)
    strict = {"spp": 4, "spp_limit": 64, "max_step_noise": 0.05}
    report = _gn(problem, u0, 16, average=0.5, **strict).reports[0]
    if not noise:
        assert calls == [(4, 4)] and "spp from step" not in report.message
        return
    # raised at the refreshes after steps 4 and 8, then at the limit
    assert calls == [(4, 4), (16, 16), (64, 64)], calls
    assert "64 spp from step 9" in report.message, report.message
    assert "glaze.roughness's step noise" in report.message
    # resumed after the raise (its state offered after step 10): it keeps the samples and says so
    saved = {}
    _gn(problem, u0, 16, offer=keep_offered(10, saved), **strict)
    del calls[:]
    resumed = _gn(problem, u0, 16, resume=saved, **strict).reports[0]
    assert calls == [(64, 64)] and "64 spp from step 9" in resumed.message
    # a limit that is not 4x a count: the last raise stops at it
    del calls[:]
    _gn(problem, u0, 16, **{**strict, "spp_limit": 24})
    assert calls == [(4, 4), (16, 16), (24, 24)], calls


@pytest.mark.parametrize("eta", [0.5, 0.02])
def test_a_relaxing_phase_ends_once_its_steps_stop_drifting(problem, monkeypatch, eta):
    """With `relaxed`, a `gn` phase whose noisy steps have relaxed to the optimum ends
    `converged` at a curvature refresh, at least `RELAXED_MIN_DETERMINED` steps in (its exact
    Jacobians' curvature is all signal), and says after how many; its result averages the last
    half of them. Steps of eta 0.02 relax about 50x slower: the phase goes on while any value
    still drifts, and ends (if it ends) only where its average is at the optimum. Without it
    the phase takes all its steps."""
    from fit.solvers.gn import RELAXED_MIN_DETERMINED

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _noisy_linear(problem, monkeypatch, truth, 0.1, [])
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.3, "glaze.ior": 1.4}
    u0 = problem.unconstrained(start)
    options = {"refresh": 10, "average": 0.5, "eta": eta}
    result = _gn(problem, u0, 200, relaxed=True, **options)
    report = result.reports[0]
    if eta == 0.5:
        assert report.outcome == Outcome.CONVERGED, report.message
        assert RELAXED_MIN_DETERMINED <= report.steps < 200 and report.steps % 10 == 0
        assert f"relaxed after {report.steps} of 200 steps" in report.message
        assert len(result.tail_gradients[0]) == report.steps // 2
    alpha = result.values["glaze.roughness"]
    if report.outcome == Outcome.CONVERGED:
        assert alpha == pytest.approx(0.05, rel=0.15), (report.message, alpha)
    else:  # still drifting at its limit: between the start and the optimum, as before
        assert report.steps == 200 and 0.05 < alpha < 0.3, alpha
    plain = _gn(problem, u0, 60, **options).reports[0]
    assert plain.outcome == Outcome.STEP_LIMIT and plain.steps == 60


@pytest.mark.parametrize("start", ["truth", "far"])
def test_a_relaxing_phase_with_nothing_to_relax_ends_sooner(problem, monkeypatch, start):
    """A relaxing phase handed on at its optimum (Adam's answer within its noise) whose
    curvature is signal (`determined`: exact Jacobians here) ends at `RELAXED_MIN_DETERMINED`
    steps where no value has a trend over all of them; one that relaxes from a far start has a
    trend over its first steps and goes on to at least `RELAXED_MIN` (a rough glaze's ior
    relaxes slowly: on the recovery sweep the sphere at alpha 0.9 ended ior -0.094 off where
    the last half of 20 steps alone was tested, -0.025 with 30)."""
    from fit.solvers.gn import RELAXED_MIN, RELAXED_MIN_DETERMINED

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _noisy_linear(problem, monkeypatch, truth, 0.1, [])
    far = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.3, "glaze.ior": 1.4}
    u0 = problem.unconstrained(truth if start == "truth" else far)
    ends = []
    for seed in range(1, 6):
        result = _gn(problem, u0, 100, seed=seed, relaxed=True, refresh=10, average=0.5)
        report = result.reports[0]
        assert report.outcome == Outcome.CONVERGED, report.message
        assert result.values["glaze.roughness"] == pytest.approx(0.05, rel=0.15)
        ends.append(report.steps)
    if start == "truth":
        # a false alarm costs a refresh or two: from the truth seeds 1-5 end at 20, 20, 40,
        # 30, 30 steps (more alarms than `TREND_ALARM`'s 20 %: the control gradient's running
        # mean correlates the steps beyond the AR(1) that `trending` allows for)
        assert ends.count(RELAXED_MIN_DETERMINED) >= 2, ends
    else:
        assert min(ends) >= RELAXED_MIN, ends


@pytest.mark.parametrize("moved", [None, 0.0, 1.0])
def test_a_relaxing_phase_whose_steps_are_clipped_has_not_relaxed(problem, monkeypatch, moved):
    """A step clipped to `max_step` that moves a value by more than a quiet step's noise
    (`largest_move` above `max_step_noise`) is not a relaxation's: `relaxed` does not end a
    phase whose last `refresh` steps had one. On the recovery sweep's sphere at alpha 0.9 (fit
    seed 0) ior's solver coordinate went back and forth by exactly `max_step` every step from
    step 11 to 20 (its linear model's step far too long); `step_noise` explains that as
    relaxation (each step a multiple of the distance before it), no trend showed, and the phase
    ended at 20 steps with ior -0.094 off (-0.025 with such steps refused). A value at its bound
    (the Cycles sphere's sigma at 0) takes clipped steps that barely move it: they do not count.
    Here the steps are taken for quiet and trendless at every check and, but with `max_step`
    at its default (`None`), every step is clipped."""
    import fit.solvers.gn as gn

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _linear(problem, monkeypatch, truth)
    monkeypatch.setattr(gn, "step_noise", lambda problem, iterates: {"glaze.roughness": 0.0})
    monkeypatch.setattr(gn, "trending", lambda iterates, eta: np.zeros(0, int))
    if moved is not None:
        monkeypatch.setattr(gn, "largest_move", lambda problem, before, after: moved)
    u0 = problem.unconstrained({**truth, "glaze.roughness": 0.2})
    options = {"relaxed": True, "refresh": 10, "average": 0.5}
    if moved is not None:
        options["max_step"] = 1e-3
    report = _gn(problem, u0, 60, **options).reports[0]
    if moved == 1.0:
        assert report.outcome == Outcome.STEP_LIMIT and report.steps == 60, report.message
    else:
        assert report.outcome == Outcome.CONVERGED, report.message


@pytest.mark.parametrize("red", [0.1, -0.2])
def test_a_value_at_its_bound_does_not_hold_a_relaxing_phase(problem, monkeypatch, red):
    """`relaxed` leaves out of its trend test a value at its bound (`pinned`): its coordinate
    wanders where the transform is flat and moves nothing (the Cycles sphere's sigma at 0 had a
    trend over 20 steps in its coordinate and held the phase to 30 steps on
    fit seed 0). Here the red pigment's coordinate is always taken for trending: with the
    optimum at red 0.1 the phase runs to its limit, with the optimum past the bound 0 (red
    ends at it) it relaxes."""
    import fit.solvers.gn as gn

    truth = {"glaze.pigment": [red, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    _linear(problem, monkeypatch, truth)
    monkeypatch.setattr(gn, "step_noise", lambda problem, iterates: {"glaze.roughness": 0.0})
    monkeypatch.setattr(gn, "trending", lambda iterates, eta: np.array([0]))
    start = {"glaze.pigment": [0.05, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    result = _gn(problem, problem.unconstrained(start), 60, relaxed=True, refresh=10)
    report = result.reports[0]
    if red > 0:
        assert report.outcome == Outcome.STEP_LIMIT and report.steps == 60, report.message
    else:
        assert result.values["glaze.pigment"][0] < 1e-3
        assert report.outcome == Outcome.CONVERGED, report.message


def test_largest_move_is_a_values_physical_change_over_its_scale(problem):
    """`largest_move`: the largest physical change of a material value between two solver
    vectors, over its `precision_scale` (alpha's and ior's values, a colour's range): a step of
    1 in alpha's coordinate at 0.05 moves it by a large share of itself; the same step of a
    colour next to its bound 0 (as the Cycles sphere's sigma) barely moves it."""
    from fit.solvers.gn import largest_move

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    u = np.asarray(problem.unconstrained(truth), np.float32)
    assert largest_move(problem, u, u) == 0.0
    step = np.zeros_like(u)
    step[3] = 1.0
    assert largest_move(problem, u, u + step) > 0.5
    colour = np.zeros_like(u)
    colour[0] = 1.0
    moved = problem.values(u + colour)["glaze.pigment"][0] - 0.1
    assert largest_move(problem, u, u + colour) == pytest.approx(moved, rel=1e-3)
    dark = {**truth, "glaze.pigment": [1e-4, 0.22, 0.55]}
    near = np.asarray(problem.unconstrained(dark), np.float32)
    assert largest_move(problem, near, near - colour) < 1e-3


def test_a_curvature_is_determined_where_every_coordinate_is_mostly_signal():
    """`determined`: every coordinate's `signal_share` at least `DETERMINED_SHARE`, the
    condition for `relaxed` to test a phase from `RELAXED_MIN_DETERMINED` steps. A glossy
    lobe's alpha, whose first Jacobians are mostly noise (the recovery sweep's torus at alpha
    0.005-0.02, fit seed 1: shares 0.45-0.49 at the first refresh, 0.14-0.34 at the second),
    can sit still for 20 steps before its steps, too short at first, relax it. Before a phase's
    first step there are no Jacobians: not determined."""
    from fit.solvers.gn import DETERMINED_SHARE, determined

    rng = np.random.default_rng(1)
    signal = rng.normal(size=(50_000, 3))
    assert not determined(None, None)
    assert determined(signal, signal)
    # noise of the signal's sd in each Jacobian: a share of 2/3, then 0.2 in one coordinate
    noisy = [signal + rng.normal(size=signal.shape) for _ in range(2)]
    assert determined(*noisy)
    for j in noisy:
        j[:, 1] = signal[:, 1] + 2 * rng.normal(size=len(j))
    assert DETERMINED_SHARE > 0.25
    assert not determined(*noisy)
    # a coordinate the images do not depend on has no signal
    blind = signal.copy()
    blind[:, 2] = 0.0
    assert not determined(blind, blind)


def test_signal_share_is_the_cross_products_part_of_the_curvature():
    """`signal_share`: 1 for two equal Jacobians, about 0 for two of independent noise alone,
    about s^2 / (s^2 + n^2 / 2) for a column of sd s plus independent noise of sd n in each;
    0 for a column that is zero in both."""
    from fit.solvers.gn import signal_share

    rng = np.random.default_rng(0)
    signal = rng.normal(size=(200_000, 3))
    signal[:, 2] = 0.0
    np.testing.assert_allclose(signal_share(signal, signal), [1.0, 1.0, 0.0])
    noise = rng.normal(size=(2, 200_000, 3))
    noise[:, :, 2] = 0.0
    share = signal_share(noise[0], noise[1])
    assert abs(share[0]) < 0.01 and abs(share[1]) < 0.01 and share[2] == 0.0
    share = signal_share(signal + noise[0], signal + noise[1])
    np.testing.assert_allclose(share[:2], 1.0 / 1.5, atol=0.01)


def test_a_relaxing_phase_tests_only_quiet_steps_since_its_last_raise(problem, monkeypatch):
    """A phase that raises its samples (`spp_limit`) does not end as relaxed while its steps
    are noisy: it tests quiet steps at its last count, at least `RELAXED_MIN_DETERMINED` of
    them (its Jacobians are exact). With noise of sd 0.5 / sqrt(spp) per pixel alpha's steps
    wander more than 10 % of it at 4 and 16 spp (34 % at 16: raised at the refreshes after
    steps 10 and 20) and are quiet at 64."""
    from fit.solvers.gn import RELAXED_MIN_DETERMINED

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    calls = []
    _noisy_linear(problem, monkeypatch, truth, 0.5, calls)
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.3, "glaze.ior": 1.4}
    u0 = problem.unconstrained(start)
    raising = {"spp": 4, "spp_limit": 64, "refresh": 10, "average": 0.5}
    result = _gn(problem, u0, 200, relaxed=True, **raising)
    report = result.reports[0]
    assert calls == [(4, 4), (16, 16), (64, 64)], calls
    assert "64 spp from step 21" in report.message, report.message
    assert report.outcome == Outcome.CONVERGED, report.message
    assert report.steps >= 20 + RELAXED_MIN_DETERMINED and report.steps % 10 == 0, report.steps
    assert result.values["glaze.roughness"] == pytest.approx(0.05, rel=0.15)
    # steps never quiet (the same noise, no raise): it takes them all
    del calls[:]
    noisy = _gn(problem, u0, 80, relaxed=True, spp=4, refresh=10, average=0.5).reports[0]
    assert noisy.outcome == Outcome.STEP_LIMIT and noisy.steps == 80, noisy.message


def test_step_noise_is_each_values_wander_as_a_share_of_its_scale(problem):
    """`step_noise`: the sd of a key's steps' noise in physical values, a share of the value
    itself for alpha (bounded away from zero) and of the range for a colour, where the iterates
    relax toward an optimum as `gn`'s do (half the way a step) plus noise; a steady relaxation
    alone has none; a rejected step (NaN) is skipped; fewer than four rows say nothing."""
    from fit.material import to_physical
    from fit.solvers.gn import step_noise

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.05, "glaze.ior": 1.52}
    u0 = np.asarray(problem.unconstrained(truth), np.float64)
    assert [f.key for f in problem.free] == ["glaze.pigment", "glaze.roughness", "glaze.ior"]
    alpha, red = 3, 0  # solver coordinates: pigment (3), alpha, ior
    rng = np.random.default_rng(1)
    sigma = np.zeros_like(u0)
    sigma[alpha], sigma[red] = 1e-3, 4e-3
    rows = [u0 + np.where(sigma > 0, 0.2, 0.0)]  # a start away from the optimum
    for _ in range(400):
        rows.append(rows[-1] - 0.5 * (rows[-1] - u0) + sigma * rng.normal(size=u0.shape))
    rows.insert(7, np.full_like(u0, np.nan))

    def physical(u):
        return np.asarray(to_physical(problem.free, np.asarray(u, np.float32)), np.float64)

    moved = physical(u0 + sigma) - physical(u0)  # a one-sigma step's change of each value
    noise = step_noise(problem, rows)
    assert noise["glaze.roughness"] == pytest.approx(moved[alpha] / 0.05, rel=0.1)
    assert noise["glaze.pigment"] == pytest.approx(moved[red], rel=0.1)  # of the range 1
    assert noise["glaze.ior"] == 0.0
    relaxing = [u0 + 0.2 * 0.5**k for k in range(10)]
    assert max(step_noise(problem, relaxing).values()) < 1e-4
    assert step_noise(problem, rows[:3]) == {}


def test_step_noise_takes_a_free_textures_noisiest_texel():
    """With a free texture (the glazed sphere's pigment as 4x4 texels beside its ior) a key's
    step noise is its noisiest texel's, as a share of the colour's range: one texel stepping
    back and forth, the rest still, gives that texel's noise and none to the ior."""
    from test_texture_trade import pigment_texture_problem

    from fit.material import to_physical
    from fit.solvers.gn import step_noise

    problem, u0 = pigment_texture_problem(4, 4)
    u0 = np.asarray(u0, np.float64)
    keys = [f.key for f in problem.free]
    assert keys == ["glaze.pigment", "glaze.ior"] and problem.free[0].size == 4 * 4 * 3
    rng = np.random.default_rng(2)
    rows = [u0.copy()]
    for _ in range(200):  # texel 5 at rest around u0[5], half the way back each step, plus noise
        row = rows[-1].copy()
        row[5] += -0.5 * (row[5] - u0[5]) + 0.01 * rng.normal()
        rows.append(row)
    moved = to_physical(problem.free, np.asarray(u0 + 0.01 * (np.arange(len(u0)) == 5), np.float32))
    moved = np.asarray(moved, np.float64) - np.asarray(to_physical(problem.free, u0), np.float64)
    noise = step_noise(problem, rows)
    assert noise[keys[0]] == pytest.approx(moved[5], rel=0.15)  # of the range 1
    assert noise[keys[1]] == 0.0
