"""Batches of fits and multi-start on a local Ray instance of 2 CPUs (one per module: Ray starts
in ~10 s), on tiny synthetic captures."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fit.batch import connect, load_batch, run_batch
from fit.commands.fit import run_fit
from fit.commands.starts import start_points
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


def test_batch_asking_more_cpus_than_any_node_fails_in_one_line(tmp_path, ray_cluster):
    """cpus_per_fit above every node's CPUs: Ray would wait forever; refused, exit 2."""
    from fit.cli import app

    sphere_capture(tmp_path / "good", 8, 6, spp=4)
    (tmp_path / "cap").mkdir()
    (tmp_path / "tiny.toml").write_text(TINY)
    spec = tmp_path / "batch.toml"
    spec.write_text(
        'configs = ["tiny.toml"]\ncaptures = ["good"]\nout = "runs"\ncpus_per_fit = 3\n'
    )
    result = CliRunner().invoke(app, ["batch", str(spec)])
    assert result.exit_code == 2, result.output
    (line,) = [x for x in result.output.splitlines() if "error:" in x]
    assert "cpus_per_fit = 3" in line and "largest: 2" in line


def test_multi_start_keeps_the_best_by_a_common_loss(tmp_path, ray_cluster):
    sphere_capture(tmp_path / "cap", 20, 15)
    (tmp_path / "fit.toml").write_text(
        TINY.replace(
            'free = ["glaze.pigment"]',
            'free = ["glaze.pigment", "glaze.ior"]\nstarts = 2\nstarts_spp = 8',
        )
    )
    cfg = load_fit_config(tmp_path / "fit.toml")
    summary = run_fit(cfg, tmp_path / "run")
    starts = summary["starts"]
    assert [s["start"] for s in starts] == [0, 1]
    assert starts[0]["start_values"]["glaze.ior"] == pytest.approx(1.52)
    assert starts[1]["start_values"]["glaze.ior"] != pytest.approx(1.52, abs=1e-3)
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


def test_a_bad_spec_is_one_line(tmp_path):
    """Unknown keys, missing configs and run-folder clashes name the spec and the key."""
    from captures.errors import InputError

    spec = tmp_path / "batch.toml"
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "fit.toml").write_text(TINY)
    (tmp_path / "b" / "fit.toml").write_text(TINY)
    for text, message in (
        ('configs = ["a/fit.toml"]\nworkers = 2\n', "batch.toml: workers: "),
        ('configs = ["nowhere.toml"]\n', "batch.toml: configs[0]: 'nowhere.toml' does not exist"),
        ('configs = ["a/fit.toml", "b/fit.toml"]\n', "share the run folder 'fit'"),
        ('configs = ["a/fit.toml"]\nkernel_cache = "~/{node}"\n', "only {host} may be filled in"),
        ('configs = ["a/fit.toml"]\nout = "a/fit.toml"\n', "out = 'a/fit.toml' is a file"),
        ('configs = ["a/fit.toml"]\nseeds = [0, 0]\n', "seeds: 0 is listed twice"),
        ('configs = ["a/fit.toml"]\nseeds = [5000000000]\n', "seeds[0]"),
        (TINY, "is a fit config, not a batch spec"),
        # a config's own mistakes, before Ray starts (each fit failed in the index after it)
        ('configs = ["c/fit.toml"]\n', "batch.toml: configs[0]: "),
        ('configs = ["c/fit.toml"]\n', "c/fit.toml: fit.phases[0].spp"),
        ('configs = ["a/fit.toml"]\n', "a/fit.toml: capture = 'cap' does not exist"),
    ):
        if "c/fit.toml" in text and not (tmp_path / "c").exists():
            (tmp_path / "c" / "cap").mkdir(parents=True)
            (tmp_path / "c" / "fit.toml").write_text(TINY.replace("spp = 2", "spp = 9999999"))
        spec.write_text(text)
        with pytest.raises(InputError, match=re.escape(message)) as err:
            load_batch(spec)
        assert "\n" not in str(err.value)


def test_a_plain_fit_does_not_import_ray():
    """With one start (the default) the fit command's modules leave Ray unimported."""
    import subprocess
    import sys

    code = "import sys, fit.cli, fit.commands.fit, fit.batch; print('ray' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"


@pytest.mark.slow
def test_four_capture_batch_resumes_after_a_kill(tmp_path):
    """`layerfit batch` as a user runs it (its own Ray instance): killed (SIGKILL) once a fit has
    finished, run again: the finished fit is skipped, the killed ones resume from their
    checkpoints, the broken capture fails alone with its one-line error, the index lists all."""
    import os
    import signal
    import subprocess
    import sys
    import time

    for k in range(3):
        sphere_capture(tmp_path / f"c{k}", 24, 18)
    sphere_capture(tmp_path / "broken", 24, 18)
    next((tmp_path / "broken").glob("*.exr")).write_bytes(b"not an image")
    (tmp_path / "cap").mkdir()
    (tmp_path / "tiny.toml").write_text(TINY.replace("steps = 3", "steps = 40"))
    spec = tmp_path / "batch.toml"
    spec.write_text(
        'configs = ["tiny.toml"]\ncaptures = ["c0", "c1", "broken", "c2"]\nout = "runs"\n'
    )
    command = [sys.executable, "-m", "fit", "batch", str(spec), "--num-cpus", "2"]
    env = {**os.environ, "COLUMNS": "200", "LAYERFIT_CHECKPOINT_SECONDS": "0.5"}
    process = subprocess.Popen(command, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    index = tmp_path / "runs" / "index.json"
    began = time.monotonic()
    while time.monotonic() - began < 300:
        assert process.poll() is None, process.communicate()
        try:
            fits = json.loads(index.read_text())["fits"]
        except (OSError, ValueError):
            fits = []
        if any(f["status"] == "done" for f in fits):
            break
        time.sleep(0.2)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    first = {f["name"]: f["status"] for f in json.loads(index.read_text())["fits"]}
    done_first = [name for name, status in first.items() if status == "done"]
    assert done_first and "submitted" in first.values()

    again = subprocess.run(command, check=False, cwd=ROOT, env=env, capture_output=True, text=True)
    assert again.returncode == 1, again.stderr
    assert "Traceback" not in again.stderr and "tiny__broken" in again.stderr
    fits = {f["name"]: f for f in json.loads(index.read_text())["fits"]}
    assert list(fits) == ["tiny__c0", "tiny__c1", "tiny__broken", "tiny__c2"]
    assert all(fits[name]["status"] == "skipped" for name in done_first)
    assert fits["tiny__broken"]["status"] == "failed" and "exr" in fits["tiny__broken"]["error"]
    for name in ("tiny__c0", "tiny__c1", "tiny__c2"):
        assert fits[name]["status"] in ("done", "skipped")
        summary = json.loads((tmp_path / "runs" / name / "summary.json").read_text())
        assert len(summary["history"]) == 40 and not summary["interrupted"]
        assert not (tmp_path / "runs" / name / "checkpoint.npz").exists()
    assert (tmp_path / "runs" / "index.html").read_text().count("report.html") == 3


@pytest.mark.slow
def test_multi_start_leaves_the_ior_valley(tmp_path, ray_cluster):
    """The glazed sphere (96x72, one view) started at ior's lower bound with a lobe sharper than
    the truth's ends in a local minimum (README "Known limits": a sharper, dimmer highlight)
    from that start alone; four starts find the truth's basin and keep it by the common loss.
    Measured alone (2026-12-06): from alpha 0.005, ior 1.01 one start ends alpha 0.0052, ior
    1.385. (From alpha 0.2 it reached the truth's basin, 1.519, since the glaze samples a
    narrow lobe at least 3 times in 4; at the lobes' weights alone it ended at 1.410.)"""
    sphere_capture(tmp_path / "cap", 96, 72, spp=512)
    (tmp_path / "fit.toml").write_text(
        'capture = "cap"\n[material]\ntype = "glaze"\npigment = [0.3, 0.3, 0.3]\n'
        'roughness = 0.005\nior = 1.01\n[fit]\nfree = ["glaze.pigment", "glaze.roughness", '
        '"glaze.ior"]\nstarts = 4\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 80\nspp = 8\ndownscale = 2\nlr = 0.1\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 120\nspp = 16\nlr = 0.03\naverage = 0.5\n'
    )
    summary = run_fit(load_fit_config(tmp_path / "fit.toml"), tmp_path / "run")
    truth = summary["truth"]["glaze.ior"]
    alone = summary["starts"][0]  # the configured start: what `layerfit fit` alone gives
    assert alone["start_values"]["glaze.ior"] == pytest.approx(1.01, abs=0.005)
    assert abs(alone["values"]["glaze.ior"] - truth) > 0.05
    assert summary["values"]["glaze.ior"] == pytest.approx(truth, abs=0.03)
    assert summary["values"]["glaze.roughness"] == pytest.approx(0.0625, rel=0.1)
    assert min(s["loss"] for s in summary["starts"]) < alone["loss"]


@pytest.mark.slow
def test_bench_schedules_run_as_ray_tasks(tmp_path, ray_cluster):
    """`layerfit bench --only fit --ray`: each schedule a task holding the whole node (2 CPUs);
    the table is the local one's (same schedules, errors against the truth)."""
    from fit.bench import fit_trade_table

    sphere_capture(tmp_path / "cap", 24, 18)
    (tmp_path / "fit.toml").write_text(
        TINY.replace('free = ["glaze.pigment"]', 'free = ["glaze.pigment", "glaze.ior"]')
    )
    names = ["default, half the steps", "Adam, then BFGS (shared seed, 64 spp)"]
    table = fit_trade_table(tmp_path / "fit.toml", names, ray=True)
    assert [row[0] for row in table.rows] == names and "Ray task" in table.notes[1]
    for row in table.rows:
        pigment_error = float(row[3].split()[0])
        assert pigment_error < 0.05  # both schedules recover the pigment at this size


def test_a_captures_folder_in_the_working_folder_hides_nothing(tmp_path):
    """Ray's workers start with the driver's working folder on `sys.path`: a user's photo folder
    named `captures/` there (a namespace package to Python) hid this project's `captures` from
    an editable install, and every batch fit failed. Importing `fit` drops such entries."""
    import subprocess
    import sys

    (tmp_path / "captures" / "cup").mkdir(parents=True)
    code = (
        "import sys; sys.path.insert(0, ''); import fit, captures; "
        "print(captures.__file__); from captures import CaptureError"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr
    assert str(tmp_path) not in result.stdout and result.stdout.strip().endswith("__init__.py")


def test_a_bad_cluster_address_is_one_line_before_ray(tmp_path):
    """An address that is not one, or where nothing answers, is refused in a few seconds naming
    the option (Ray itself waited minutes printing its own log lines, or raised an internal
    error)."""
    from captures.errors import InputError
    from fit.cluster import check_address

    check_address(None)
    check_address("auto")
    with pytest.raises(InputError, match=r"--address 'not a host::x': not a cluster address"):
        check_address("not a host::x")
    with pytest.raises(InputError, match=r"RAY_ADDRESS 127.0.0.1:1: no Ray cluster answers"):
        check_address("127.0.0.1:1", "RAY_ADDRESS")


def test_a_batch_folder_keeps_a_users_files_and_other_batches(tmp_path):
    """The index is written into `out` before any fit: a folder holding a user's files (their
    own index.html too) or another spec's batch is refused, naming the spec and `out`."""
    from captures.errors import InputError

    (tmp_path / "a" / "cap").mkdir(parents=True)
    (tmp_path / "a" / "fit.toml").write_text(TINY)
    mine = tmp_path / "mydocs"
    mine.mkdir()
    (mine / "index.html").write_text("the user's own")
    spec = tmp_path / "batch.toml"
    spec.write_text('configs = ["a/fit.toml"]\nout = "mydocs"\n')
    with pytest.raises(InputError, match=r"batch.toml: out = 'mydocs' holds files .*index.html"):
        load_batch(spec)
    (mine / "index.html").unlink()
    (mine / "index.json").write_text(json.dumps({"spec": str(tmp_path / "other.toml")}))
    with pytest.raises(InputError, match=r"holds another batch's index \(.*other.toml\)"):
        load_batch(spec)
    (mine / "index.json").write_text(json.dumps({"spec": str(spec)}))
    (mine / "index.html").write_text("this batch's own")
    assert [job.name for job in load_batch(spec).jobs] == ["fit"]


def test_only_a_matching_finished_summary_skips_a_fit(tmp_path):
    """A run folder is skipped only for a finished summary of the same config and seed; one
    that is not a summary, or of another config, runs again (was: an internal error, or another
    config's results credited)."""
    from fit.batch.runner import finished

    (tmp_path / "a" / "cap").mkdir(parents=True)
    (tmp_path / "a" / "fit.toml").write_text(TINY)
    (tmp_path / "a" / "other.toml").write_text(TINY)
    spec = tmp_path / "batch.toml"
    spec.write_text('configs = ["a/fit.toml"]\nseeds = [3]\n')
    (job,) = load_batch(spec).jobs
    job.out.mkdir(parents=True)
    summary = {"interrupted": False, "values": {}, "error": {}, "seed": 3}
    for text in ("[1, 2]", json.dumps({**summary, "error": "oops"})):
        (job.out / "summary.json").write_text(text)
        assert finished(job.out, job) is None
    (job.out / "summary.json").write_text(json.dumps({**summary, "config": str(job.config)}))
    assert finished(job.out, job) is not None
    other = {**summary, "config": str(tmp_path / "a" / "other.toml")}
    (job.out / "summary.json").write_text(json.dumps(other))
    assert finished(job.out, job) is None
    (job.out / "summary.json").write_text(
        json.dumps({**summary, "config": str(job.config), "seed": 4})
    )
    assert finished(job.out, job) is None


def test_an_edited_config_runs_its_finished_fit_again(tmp_path):
    """A finished fit is skipped while its config asks for the same (its settings, seed,
    capture, starting material: `config_identity`, saved in the summary); edited since (a
    phase's steps, the starting roughness, the free keys), it runs again. It was skipped,
    its results those of the old config."""
    from fit.batch.runner import finished
    from fit.config import config_identity, load_fit_config

    (tmp_path / "a" / "cap").mkdir(parents=True)
    config = tmp_path / "a" / "fit.toml"
    config.write_text(TINY)
    spec = tmp_path / "batch.toml"
    spec.write_text('configs = ["a/fit.toml"]\n')
    (job,) = load_batch(spec).jobs
    job.out.mkdir(parents=True)
    cfg = load_fit_config(config)
    summary = {"interrupted": False, "values": {}, "error": {}, "seed": 0}
    summary |= {"config": str(config), "config_identity": config_identity(cfg)}
    (job.out / "summary.json").write_text(json.dumps(summary))
    assert finished(job.out, job) is not None
    for old, new in (
        ("steps = 3", "steps = 4"),
        ("roughness = 0.0625", "roughness = 0.1"),
        ('free = ["glaze.pigment"]', 'free = ["glaze.pigment", "glaze.ior"]'),
    ):
        config.write_text(TINY.replace(old, new))
        assert finished(job.out, job) is None, new
    config.write_text("# a comment changes nothing\n" + TINY)
    assert finished(job.out, job) is not None


def test_a_run_folder_that_is_not_a_run_is_said_for_a_batch(tmp_path, monkeypatch):
    """In a batch (no --out, no --force) a job's folder holding other files, or a checkpoint
    that cannot be read, says what to do there; an unmakeable kernel cache names its key."""
    from captures.errors import InputError
    from fit.batch.runner import _check_run_folder
    from fit.cluster import prepare_worker

    run = tmp_path / "run"
    assert _check_run_folder(run) is False
    run.mkdir()
    (run / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"holds files that are not a run's \(notes.txt\)"):
        _check_run_folder(run)
    (run / "checkpoint.npz").write_bytes(b"junk")
    with pytest.raises(InputError, match=r"checkpoint.npz: unreadable.*delete it"):
        _check_run_folder(run)
    (tmp_path / "afile").write_text("x")
    monkeypatch.delenv("DRJIT_CACHE_DIR", raising=False)
    with pytest.raises(InputError, match=r"kernel_cache = .*afile"):
        prepare_worker(1, None, str(tmp_path / "afile" / "{host}"))


def test_a_batch_is_found_again_from_another_folder_and_a_template_config(tmp_path, monkeypatch):
    """The index kept the spec's path as typed: run again from another folder, the batch was
    refused as "another batch's". A config whose own capture is a template (absent) made its
    finished fit in the spec's captures run again every time."""
    from fit.batch.runner import finished, write_index

    shelf = tmp_path / "shelf"
    (shelf / "c1").mkdir(parents=True)
    (shelf / "fit.toml").write_text(TINY.replace('capture = "cap"', 'capture = "template"'))
    (shelf / "spec.toml").write_text('configs = ["fit.toml"]\ncaptures = ["c1"]\n')
    monkeypatch.chdir(shelf)
    batch = load_batch("spec.toml")
    write_index(batch, [])
    monkeypatch.chdir(tmp_path)
    (job,) = load_batch("shelf/spec.toml").jobs  # was: holds another batch's index
    job.out.mkdir(parents=True)
    summary = {"interrupted": False, "values": {}, "error": {}, "seed": 0}
    summary |= {"config": str(job.config), "capture": str(job.capture)}
    (job.out / "summary.json").write_text(json.dumps(summary))
    assert finished(job.out, job) is not None


def test_batch_spec_names_for_manifests_and_odd_values(tmp_path):
    """Captures given as manifest files are named by their stems (`caps/bowl.toml` and
    `caps/vase.toml` both were `caps`, and refused); a kernel cache with a field or index of
    {host}, and an out with a NUL, are one line (they were internal errors)."""
    from captures.errors import InputError

    (tmp_path / "caps").mkdir()
    for name in ("bowl", "vase"):  # manifests beside each other (their fits open them)
        (tmp_path / "caps" / f"{name}.toml").write_text("[capture]\n")
    (tmp_path / "cap").mkdir()
    (tmp_path / "fit.toml").write_text(TINY)
    spec = tmp_path / "batch.toml"
    spec.write_text('configs = ["fit.toml"]\ncaptures = ["caps/bowl.toml", "caps/vase.toml"]\n')
    assert [j.name for j in load_batch(spec).jobs] == ["fit__bowl", "fit__vase"]
    for text, message in (
        ('configs = ["fit.toml"]\nkernel_cache = "~/{host.x}"\n', "only {host} may be filled"),
        ('configs = ["fit.toml"]\nkernel_cache = "~/{host[x]}"\n', "only {host} may be filled"),
        ('configs = ["fit.toml"]\nout = "a\\u0000b"\n', "holds a NUL character"),
    ):
        spec.write_text(text)
        with pytest.raises(InputError, match=re.escape(message)):
            load_batch(spec)


def test_the_index_names_a_configs_own_seed():
    """A fit whose spec gives no seed runs at its config's: the index's seed column shows it
    (it was blank)."""
    from fit.batch.runner import _csv, summary_entry

    summary = {"interrupted": False, "values": {"glaze.ior": 1.5}, "error": {}, "seed": 7}
    entry = {"name": "fit", "status": "done", "seed": None} | summary_entry(summary)
    assert entry["seed"] == 7
    assert _csv([entry]).splitlines()[1].split(",")[4] == "7"
    assert "seed" not in summary_entry({**summary, "seed": None})


def test_the_index_names_a_fits_warnings():
    """A fit with a poorly determined parameter or a value at its bound says so in the index's
    warnings column (CSV and HTML), so a batch's suspicious fits show before their numbers; a
    clean fit's cell is empty."""
    from fit.batch.runner import COLUMNS, _csv, summary_entry

    summary = {
        "values": {"glaze.ior": 1.011},
        "error": {},
        "poorly_determined": ["glaze.ior"],
        "at_bounds": [{"parameter": "glaze.ior", "bound": "lower", "value": 1.011}],
    }
    entry = {"name": "fit", "status": "done"} | summary_entry(summary)
    said = "poorly determined: glaze.ior; at its lower bound: glaze.ior"
    assert entry["warnings"] == said
    assert said in _csv([entry]) and "warnings" in COLUMNS  # the HTML's columns are COLUMNS
    assert summary_entry({"values": {}, "error": {}})["warnings"] == ""


def test_a_capture_that_cannot_be_one_stops_the_batch_before_ray(tmp_path):
    """A capture.toml that is not valid TOML, or a fit config given as a capture: refused by
    the spec's file and index before Ray starts, exit 2 (each was its fit's failure, after the
    other fits had run)."""
    from captures.errors import InputError

    (tmp_path / "cap").mkdir()
    (tmp_path / "fit.toml").write_text(TINY)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "capture.toml").write_text("[capture\n")
    spec = tmp_path / "batch.toml"
    for captures, message in (
        ('["cap", "bad"]', r"batch.toml: captures\[1\]: .*bad/capture.toml"),
        ('["fit.toml"]', r"captures\[0\]: .*fit.toml: is a fit config, not a capture manifest"),
    ):
        spec.write_text(f'configs = ["fit.toml"]\ncaptures = {captures}\n')
        with pytest.raises(InputError, match=message):
            load_batch(spec)


def test_a_one_cpu_worker_loads_an_exr_texture(tmp_path):
    """A worker prepared for one CPU (a `--starts` fit's task, a batch's) loads an EXR bitmap,
    as the cup's masks and a free texture's start are: with Dr.Jit's thread count at 1 Mitsuba
    3.9 never returned from it (the cup's `--starts 2` hung). In a fresh process, so that a hang
    fails this test instead of the suite."""
    import subprocess
    import sys

    from captures.images import write_image

    write_image(tmp_path / "mask.exr", np.full((4, 8, 1), 0.25, np.float32))
    script = (
        "import sys, numpy as np\n"
        "from fit.cluster import prepare_worker\n"
        "prepare_worker(1, None)\n"
        "from fit.material.free import texture_data\n"
        "t = texture_data({'type': 'bitmap', 'filename': sys.argv[1], 'raw': True})\n"
        "assert t.shape == (4, 8, 1) and np.allclose(t, 0.25), t\n"
    )
    try:
        done = subprocess.run(
            [sys.executable, "-c", script, str(tmp_path / "mask.exr")],
            check=False,
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    except subprocess.TimeoutExpired:
        pytest.fail("loading an EXR texture in a one-CPU worker hung for 120 s")
    assert done.returncode == 0, done.stderr[-2000:]
