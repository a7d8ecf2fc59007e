"""`layerfit fit` end to end on a small synthetic capture: table, summary.json, loss plot."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
from cli_run import run_cli

from fit.commands.synth import synthesize
from fit.config import load_render_config

ROOT = Path(__file__).resolve().parents[2]


def test_fit_command(tmp_path):
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=40, height=30)
    synthesize(
        dataclasses.replace(cfg.scene, cameras=(camera,)),
        cfg.material,
        tmp_path / "cap",
        spp=256,
        seed=4,
    )
    (tmp_path / "fit.toml").write_text(
        'capture = "cap"\n'
        '[material]\ntype = "glaze"\npigment = [0.4, 0.4, 0.4]\nroughness = 0.0625\nior = 1.52\n'
        '[fit]\nfree = ["glaze.pigment"]\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 30\nspp = 8\ndownscale = 2\nlr = 0.1\n'
        '[[fit.phases]]\nsolver = "bfgs"\nsteps = 10\nspp = 32\n'
    )
    out = run_cli("fit", tmp_path / "fit.toml", "--out", tmp_path / "result")
    assert out.returncode == 0, out.stderr
    assert "glaze.pigment" in out.stderr and "adam+bfgs" in out.stderr
    summary = json.loads((tmp_path / "result" / "summary.json").read_text())
    assert summary["truth"]["glaze.pigment"] == [0.1, 0.22, 0.55]
    np.testing.assert_allclose(summary["values"]["glaze.pigment"], [0.1, 0.22, 0.55], atol=0.02)
    assert [p["solver"] for p in summary["phases"]] == ["adam", "bfgs"]
    assert len(summary["history"]) == 31  # the Adam steps, then the BFGS phase's final loss
    assert summary["wall_time_s"] > 0 and len(summary["std"]["glaze.pigment"]) == 3
    assert (tmp_path / "result" / "loss.png").stat().st_size > 1000
    assert (tmp_path / "result" / "fit.png").stat().st_size > 1000


def test_fit_command_bad_config(tmp_path):
    (tmp_path / "fit.toml").write_text(
        'capture = "nowhere"\n[material]\ntype = "glaze"\n[fit]\nfree = ["glaze.ior"]\n'
    )
    out = run_cli("fit", tmp_path / "fit.toml", timeout=300)
    assert out.returncode == 2
    assert "fit.toml: capture = 'nowhere' does not exist" in out.stderr


def test_fit_command_bad_phase_resolution(tmp_path):
    """A phase whose downscale does not divide the photos fails before any work, naming it."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=40, height=30)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    synthesize(scene, cfg.material, tmp_path / "cap", spp=4, seed=4)
    (tmp_path / "fit.toml").write_text(
        'capture = "cap"\n[material]\ntype = "glaze"\n[fit]\nfree = ["glaze.ior"]\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 10\nspp = 8\ndownscale = 3\n'
    )
    out = run_cli("fit", tmp_path / "fit.toml", "--out", tmp_path / "result", timeout=300)
    assert out.returncode == 2
    assert "fit.toml: fit.phases[0].downscale:" in out.stderr
    assert "does not divide the image size 40x30" in out.stderr
    assert not (tmp_path / "result").exists()
