"""Batches of fits and multi-start on a local Ray instance of 2 CPUs (one per module: Ray starts
in ~10 s), on tiny synthetic captures."""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fit.batch import connect, load_batch, run_batch
from fit.batch.starts import start_points
from fit.commands.fit import run_fit
from fit.commands.synth import synthesize
from fit.config import load_fit_config, load_render_config
from fit.material import resolve
from fit.solvers import Problem

ROOT = Path(__file__).resolve().parents[2]

TINY = (
    'capture = "cap"\n'
    '[material]\ntype = "glaze"\npigment = [0.4, 0.4, 0.4]\nroughness = 0.0625\nior = 1.52\n'
    '[fit]\nfree = ["glaze.pigment"]\nuncertainty_spp = 4\n'
    '[[fit.phases]]\nsolver = "adam"\nsteps = 3\nspp = 2\nlr = 0.1\n'
)


@pytest.fixture(scope="module")
def ray_cluster():
    """One local Ray instance (2 CPUs) for the module."""
    with connect(num_cpus=2):
        yield


def sphere_capture(folder: Path, width: int, height: int, spp: int = 64) -> Path:
    """The glazed sphere (configs/glazed-sphere.toml, its truth) from one camera."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=width, height=height)
    synthesize(dataclasses.replace(cfg.scene, cameras=(camera,)), cfg.material, folder, spp, 4)
    return folder


def test_batch_isolates_a_broken_capture_writes_its_index_and_resumes(tmp_path, ray_cluster):
    sphere_capture(tmp_path / "good", 20, 15)
    sphere_capture(tmp_path / "bad", 20, 15)
    image = next((tmp_path / "bad").glob("*.exr"))
    image.write_bytes(b"not an image")
    (tmp_path / "cap").mkdir()  # the config's own capture, replaced by the spec's
    (tmp_path / "tiny.toml").write_text(TINY)
    spec = tmp_path / "batch.toml"
    spec.write_text('configs = ["tiny.toml"]\ncaptures = ["good", "bad"]\nout = "runs"\n')
    batch = load_batch(spec)
    assert [j.name for j in batch.jobs] == ["tiny__good", "tiny__bad"]

    seen = []
    entries = run_batch(batch, lambda entry, done, total: seen.append((entry["name"], done)))
    by_name = {e["name"]: e for e in entries}
    assert by_name["tiny__good"]["status"] == "done"
    assert by_name["tiny__bad"]["status"] == "failed"
    error = by_name["tiny__bad"]["error"]
    assert image.name in error and "\n" not in error
    assert sorted(done for _, done in seen) == [1, 2]
    runs = tmp_path / "runs"
    summary = json.loads((runs / "tiny__good" / "summary.json").read_text())
    assert by_name["tiny__good"]["loss"] == summary["loss"]
    assert summary["capture"] == str(tmp_path / "good")
    index = json.loads((runs / "index.json").read_text())
    assert index["counts"]["done"] == 1 and index["counts"]["failed"] == 1
    rows = list(csv.DictReader((runs / "index.csv").read_text().splitlines()))
    assert [r["status"] for r in rows] == ["done", "failed"] and rows[1]["error"] == error
    page = (runs / "index.html").read_text()
    assert 'href="tiny__good/report.html"' in page and page.count("report.html") == 1

    # Again, through the command: the finished fit is skipped, the broken one fails again
    from fit.cli import app

    result = CliRunner().invoke(app, ["batch", str(spec)])
    assert result.exit_code == 1, result.output
    assert "1 already done, 1 failed" in result.output and "tiny__bad" in result.output
    again = json.loads((runs / "index.json").read_text())
    assert [f["status"] for f in again["fits"]] == ["skipped", "failed"]
    assert json.loads((runs / "tiny__good" / "summary.json").read_text()) == summary


def test_multi_start_keeps_the_best_by_a_common_loss(tmp_path, ray_cluster):
    sphere_capture(tmp_path / "cap", 20, 15)
    (tmp_path / "fit.toml").write_text(
        TINY.replace(
            'free = ["glaze.pigment"]',
            'free = ["glaze.pigment", "glaze.ior"]\nstarts = 3\nstarts_spp = 8',
        )
    )
    cfg = load_fit_config(tmp_path / "fit.toml")
    summary = run_fit(cfg, tmp_path / "run")
    starts = summary["starts"]
    assert [s["start"] for s in starts] == [0, 1, 2]
    assert starts[0]["start_values"]["glaze.ior"] == pytest.approx(1.52)
    assert len({round(s["start_values"]["glaze.ior"], 4) for s in starts}) == 3
    best = [s for s in starts if s["best"]]
    assert len(best) == 1 and best[0]["loss"] == min(s["loss"] for s in starts)
    assert summary["values"]["glaze.ior"] == pytest.approx(best[0]["values"]["glaze.ior"])
    assert (tmp_path / "run" / "report.html").exists()


def test_start_points_leave_a_bound():
    """Starts spread around a start at ior's lower bound reach the plausible range (the centre
    is pulled off the sigmoid's flat end), and start 0 is the configured start."""
    material = load_render_config(ROOT / "configs" / "glazed-sphere.toml").material
    problem = Problem(None, material, resolve(material, ["glaze.ior"]))
    points = start_points(problem, {"glaze.ior": 1.01}, 4, 1.5, seed=0)
    iors = [problem.values(u)["glaze.ior"] for u in points]
    assert iors[0] == pytest.approx(1.01, abs=0.002)
    assert max(iors) > 1.4 and len(set(np.round(iors, 3))) == 4
