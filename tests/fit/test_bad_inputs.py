"""Bad inputs fail before any work: exit status 2, one line naming the file, field and fix."""

from __future__ import annotations

import re
import shutil

import pytest
from bad_capture_cases import CAPTURE_CASES
from bad_command_cases import COMMAND_CASES
from bad_fit_cases import FIT_CASES
from bad_inputs_cases import Case, edit, run, snapshot

CASES: list[Case] = [*COMMAND_CASES, *CAPTURE_CASES, *FIT_CASES]


@pytest.mark.parametrize("make, expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(base, tmp_path, capsys, make, expected):
    work = tmp_path / "w"
    shutil.copytree(base, work)
    args = make(work)
    before = snapshot(work)
    code, stdout, stderr = run(args, capsys)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert "Traceback" not in stderr and "internal error" not in stderr and not stdout.strip()
    assert "; " in lines[0], f"no fix given: {lines[0]}"
    for text in expected:
        assert text in lines[0], (text, lines[0])
    assert snapshot(work) == before  # inputs byte-identical, no partial or new file


def test_corpus_is_large_and_ids_unique():
    assert len(CASES) >= 80 and len({c[0] for c in CASES}) == len(CASES)


def test_help_shows_bracketed_text(capsys):
    code, stdout, _ = run(["synth", "--help"], capsys)
    assert code == 0 and "[truth]" in stdout and "[scene]" in stdout
    code, stdout, _ = run(["fit", "--help"], capsys)
    assert code == 0 and "capture, material, fit" in stdout


def test_a_truth_key_no_parameter_can_have_is_named(base, tmp_path):
    """`"glaze.base color"` in `[truth]` was an internal error (KeyError) in the fit."""
    from captures import CaptureError
    from fit.commands.fit import prepare
    from fit.config import load_fit_config

    work = tmp_path / "w"
    shutil.copytree(base, work)
    edit(work / "cap" / "capture.toml", '"glaze.roughness" =', '"glaze.base color" =')
    with pytest.raises(CaptureError, match=r"truth\.glaze\.base color: not a parameter key"):
        prepare(load_fit_config(work / "fit.toml"))


def test_force_never_replaces_the_fits_starting_preset(base, tmp_path):
    """A fit starting from a run's preset.toml, written with --force into that run folder,
    replaced the preset it started from; it is an input like the config and the capture."""
    from captures import InputError
    from fit.commands.prepare import check_output
    from fit.config import load_fit_config

    work = tmp_path / "w"
    shutil.copytree(base, work)
    run = work / "runA"
    run.mkdir()
    shutil.copy(work / "preset.toml", run / "preset.toml")
    text = (work / "fit.toml").read_text()
    head, rest = text.split("[material]", 1)
    (work / "again.toml").write_text(
        head + 'material = "runA/preset.toml"\n[fit]' + rest.split("[fit]", 1)[1]
    )
    cfg = load_fit_config(work / "again.toml")
    with pytest.raises(InputError, match="holds the fit's inputs"):
        check_output(run, cfg, resume=False, force=True)


def test_resume_refuses_a_checkpoint_of_another_capture_material_or_loss(base, tmp_path):
    """A checkpoint's identity held the free keys, views, phases and seed only: one saved on
    another capture with the same view names, another starting material or another loss was
    resumed without a word (its history then mixed two losses)."""
    from captures import InputError
    from fit.commands.prepare import check_resume, fit_identity, prepare
    from fit.config import load_fit_config
    from fit.solvers import Checkpoint

    cfg = load_fit_config(base / "fit.toml")
    prepared = prepare(cfg, trace=False)
    u = prepared.problem.unconstrained(prepared.start)
    ours = fit_identity(prepared, cfg)
    changes = {
        "capture": ("capture", "/elsewhere/cap"),
        "starting material": ("starting material", {"type": "glaze", "roughness": 0.3}),
        "loss": ("loss, loss_scale, gains, downscale or holdout", ["cauchy", None, False, 1, 0]),
    }
    for key, (named, value) in changes.items():
        run = tmp_path / key.replace(" ", "_")
        run.mkdir()
        checkpoint = Checkpoint(run / "checkpoint.npz")
        checkpoint.identity = {**ours, key: value}
        checkpoint.latest = {"phase": 0, "u_phase": u, "history_before": [], "ends": []}
        checkpoint.latest["reports"] = []
        checkpoint.flush()
        with pytest.raises(InputError, match=f"saved by a fit with other {re.escape(named)}"):
            check_resume(prepared, cfg, run)
    same = tmp_path / "same"
    same.mkdir()
    checkpoint = Checkpoint(same / "checkpoint.npz")
    checkpoint.identity = ours
    checkpoint.latest = {"phase": 0, "u_phase": u, "history_before": [], "ends": [], "reports": []}
    checkpoint.flush()
    check_resume(prepared, cfg, same)  # its own: accepted


def test_a_layer_named_alone_in_free_says_to_name_its_parameters():
    """free = ["glaze"] said "no layer '' is built (built: glaze)"."""
    from fit.material import resolve
    from fit.material.build import build_material

    material = build_material({"type": "glaze"})
    with pytest.raises(KeyError, match=r"'glaze' is a layer; name its parameters: glaze\.pigment"):
        resolve(material, ["glaze"])


def test_inspect_in_a_capture_folder_names_its_default_sheet(base, tmp_path, capsys, monkeypatch):
    """`layerfit inspect .` inside a capture: the default sheet was `out/inspect-.png`, and its
    refusal blamed a `--sheet` never given; named after the folder, and said to be the default.
    From elsewhere the folder's own name is used."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    monkeypatch.chdir(work / "cap")
    code, _, stderr = run(["inspect", ".", "--no-silhouette"], capsys)
    assert code == 2
    assert "the default sheet out/inspect-cap.png (give --sheet): is inside the capture" in stderr
    monkeypatch.chdir(work)
    code, _, stderr = run(["inspect", "cap/capture.toml", "--no-silhouette"], capsys)
    assert code == 0, stderr
    assert (work / "out" / "inspect-cap.png").is_file()
