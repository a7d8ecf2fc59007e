"""Fit configs: the bundled ones load; mistakes name the file and the key."""

from __future__ import annotations

from pathlib import Path

import pytest

from captures import InputError
from fit.config import load_fit_config
from fit.material import resolve, start_values
from fit.solvers import DEFAULT_SCHEDULE

ROOT = Path(__file__).resolve().parents[2]


def test_peer_config_loads(shared_data):
    cfg = load_fit_config(ROOT / "configs" / "peer-sphere.toml")
    assert cfg.capture.name == "scene.json" and cfg.material.bsdf["fresnel"] == "exact"
    free = resolve(cfg.material, cfg.free)
    assert start_values(free) == {
        "glaze.pigment": [0.5, 0.5, 0.5],
        "glaze.roughness": 0.2,
        "glaze.ior": 1.3,
        "glaze.sigma": 0.3,
    }


PHASES = """
[[fit.phases]]
solver = "adam"
steps = 100
spp = 8
downscale = 2
lr = 0.1
[[fit.phases]]
solver = "lm"
steps = 5
spp = 128
jacobian_spp = 16
"""


def test_phases_load_and_default(tmp_path, shared_data):
    text = (ROOT / "configs" / "peer-sphere.toml").read_text()
    path = tmp_path / "fit.toml"
    path.write_text(text.replace('"../../shared/data', f'"{shared_data}') + PHASES)
    phases = load_fit_config(path).phases
    assert [(p.solver, p.steps, p.spp, p.downscale) for p in phases] == [
        ("adam", 100, 8, 2),
        ("lm", 5, 128, 1),
    ]
    assert phases[0].lr == 0.1 and phases[1].jacobian_spp == 16
    # its resolution against the full photos: with fit.downscale = 4 a half-resolution phase
    # is an eighth (the progress bar and the report's legend said "1/2 res")
    assert phases[0].describe() == "adam, 8 spp, 1/2 res"
    assert phases[0].describe(4) == "adam, 8 spp, 1/8 res"
    assert load_fit_config(ROOT / "configs" / "peer-sphere.toml").phases == list(DEFAULT_SCHEDULE)


def test_default_schedule_holds_free_mask_thresholds_first():
    """With a mask threshold free, the default's Adam steps are split: the first 30 hold every
    threshold, the rest free them; the steps, samples and later phases stay the default's. A
    config's own phases are taken as written."""
    from fit.config.models import FitSettings

    assert FitSettings(free=["glaze.roughness"]).phases == list(DEFAULT_SCHEDULE)
    phases = FitSettings(free=["glaze.roughness", "stain.mask.threshold"]).phases
    held, freed, *rest = phases
    assert held.options.hold == ("*.mask.threshold",) and freed.options.hold == ()
    assert held.steps + freed.steps == DEFAULT_SCHEDULE[0].steps and held.steps == 30
    for p in (held, freed):
        assert (p.solver, p.spp, p.downscale, p.lr) == ("adam", 8, 2, DEFAULT_SCHEDULE[0].lr)
    assert rest == list(DEFAULT_SCHEDULE[1:])
    own = FitSettings(
        free=["lime.mask.threshold"], phases=[{"solver": "adam", "steps": 3, "spp": 2}]
    )
    assert len(own.phases) == 1 and own.phases[0].options.hold == ()


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            ('solver = "lm"', 'solver = "newton"'),
            "fit.phases[1].solver: got 'newton'; choose one of",
        ),
        (("spp = 128", "spp = 0"), "fit.phases[1].spp: got 0; should be greater than 0"),
        (("jacobian_spp = 16", "lr = 0.1"), "fit.phases[1].lr: does not apply to solver = 'lm'"),
        (
            ("lr = 0.1", "average = 2"),
            "fit.phases[0].average: got 2; should be less than or equal to 1",
        ),
        (("steps = 5\n", ""), "fit.phases[1].steps: missing"),
        (("[fit]", "[fit]\nfree_params = 1"), "fit.free_params: unknown key; known: free"),
        (("[fit]", '[fit]\nloss = "l1"'), "fit.loss: got 'l1'; choose one of"),
        (('scene.json"', 'nothing.json"'), "nothing.json' does not exist"),
    ],
)
def test_fit_config_errors(tmp_path, shared_data, edit, message):
    text = (ROOT / "configs" / "peer-sphere.toml").read_text() + PHASES
    text = text.replace('"../../shared/data', f'"{shared_data}')  # the copy lives elsewhere
    assert edit[0] in text
    path = tmp_path / "broken.toml"
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(InputError) as err:
        load_fit_config(path)
    assert message in str(err.value) and "broken.toml" in str(err.value)


def test_default_job_configs(tmp_path):
    """scripts/run.sh's configs: the 3-view scene replaces the glazed sphere's for `synth`, and
    the fit config loads against the capture it makes (rendered here at 1 spp)."""
    from captures import parse_scene
    from captures.schema import load_toml
    from fit.commands.synth import synthesize
    from fit.config import load_render_config

    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    views = ROOT / "configs" / "glazed-sphere-views.toml"
    scene = parse_scene(load_toml(views, "file")["scene"], views)  # as `synth --scene` does
    assert [(c.width, c.height) for c in scene.cameras] == [(160, 120)] * 3
    synthesize(scene, cfg.material, tmp_path / "out" / "glazed-sphere-capture", spp=1)
    text = (ROOT / "configs" / "glazed-sphere-fit.toml").read_text()
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "fit.toml").write_text(text)
    fit = load_fit_config(tmp_path / "configs" / "fit.toml")
    assert fit.phases == list(DEFAULT_SCHEDULE)
    assert [f.key for f in resolve(fit.material, fit.free)] == fit.free


def test_fitting_guide_shows_the_default_schedule_exactly():
    """docs/fitting.md's config example ("The fit config") says its phases are exactly the
    default schedule."""
    import tomllib

    from fit.solvers import Phase

    text = (ROOT / "docs" / "fitting.md").read_text()
    fitting = text[text.index("\n## The fit config\n") :]
    block = fitting[
        fitting.index("```toml\n") + 8 : fitting.index("```", fitting.index("```toml") + 7)
    ]
    assert "The default schedule is exactly this" in fitting

    def key(p):  # options as the solver sees them (defaults filled in)
        return (p.solver, p.steps, p.spp, p.downscale, p.options)

    phases = [Phase(**p) for p in tomllib.loads(block)["fit"]["phases"]]
    assert [key(p) for p in phases] == [key(p) for p in DEFAULT_SCHEDULE]
