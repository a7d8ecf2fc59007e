"""Inputs taken with a warning: a truth typo, clipped or NaN pixels, one view's gains, big fits."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from bad_inputs_cases import edit, run

from captures.images import write_image


def test_a_truth_typo_is_a_warning_not_silence(base, tmp_path, caplog):
    """A `[truth]` key that names no parameter of the fitted material is not scored: a warning
    names it (with the key it was probably meant to be), before any render."""
    import logging

    from fit.commands.fit import prepare
    from fit.config import load_fit_config

    work = tmp_path / "w"
    shutil.copytree(base, work)
    edit(work / "cap" / "capture.toml", '"glaze.roughness" =', '"glaze.roughnes" =')
    with caplog.at_level(logging.WARNING):
        prepare(load_fit_config(work / "fit.toml"))
    (message,) = [r.getMessage() for r in caplog.records if "truth" in r.getMessage()]
    assert "truth.glaze.roughnes" in message and "did you mean glaze.roughness?" in message
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # the untouched capture: no warning
        prepare(load_fit_config(base / "fit.toml"))
    assert not [r for r in caplog.records if "truth" in r.getMessage()]


def test_a_gains_truth_is_scored_only_where_a_gain_is_fitted(base, caplog):
    """`gain.<view>` in `[truth]` was warned "not scored" and scored all the same; of another
    size than the fitted gain it failed after the whole fit (an internal error). Now: the
    fitted gain's size or an error before any work; without a fitted gain, a warning and
    left out of the scores."""
    import logging

    from captures import CaptureError
    from captures.capture import load_capture
    from fit.commands.prepare import check_truth

    capture = load_capture(base / "cap")
    capture.truth["gain.view_00"] = [1.0, 2.0]
    with pytest.raises(CaptureError, match=r"truth\.gain\.view_00: has 2 value\(s\) but the fit"):
        check_truth(capture, [], "cap", None, {"view_00": 3})
    capture.truth["gain.view_00"] = [1.0, 1.0, 1.0]
    check_truth(capture, [], "cap", None, {"view_00": 3})
    assert capture.truth["gain.view_00"] == [1.0, 1.0, 1.0]  # scored
    capture.truth["gain.view_09"] = 1.0
    with caplog.at_level(logging.WARNING):
        check_truth(capture, [], "cap", None, {"view_00": 3})
    assert "truth.gain.view_09: not scored (no fitted view view_09)" in caplog.text
    assert "gain.view_09" not in capture.truth
    with caplog.at_level(logging.WARNING):
        check_truth(capture, [], "cap", None, {})
    assert "truth.gain.view_00: not scored (gains are not fitted" in caplog.text
    assert "gain.view_00" not in capture.truth


def test_a_capture_warning_is_said_once(base, tmp_path, capfd):
    """A view's warning (here a NaN pixel) is one `warning:` line on stderr, not two."""
    import subprocess
    import sys

    work = tmp_path / "w"
    shutil.copytree(base, work)
    image = np.full((12, 16, 3), 0.2, np.float32)
    image[3, 4] = np.nan
    write_image(work / "cap" / "view_00.exr", image)
    code = (
        "import sys; from fit.entry import run as main; "
        f"main(['inspect', {str(work / 'cap')!r}, '--no-silhouette', '--sheet', "
        f"{str(work / 's.png')!r}])"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if "NaN" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: "), result.stderr


def test_synth_warns_of_clipped_photographs(base, tmp_path, caplog):
    """A synthetic PNG whose pixels clip (a bright light, a high exposure) is said at once, with
    the option that fixes it (a user found most of a torus masked out only in `inspect`)."""
    import logging

    from fit.commands.synth import Degradation, synthesize
    from fit.config import load_render_config

    cfg = load_render_config(base / "render.toml")

    def warnings(name: str, base_ev: float) -> list[str]:
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            degradation = Degradation(base_ev=base_ev)
            synthesize(
                cfg.scene, cfg.material, tmp_path / name, 2, fmt="png", degradation=degradation
            )
        return [r.getMessage() for r in caplog.records]

    assert any("clip" in m and "--exposure-base" in m for m in warnings("bright", 6.0))
    assert not [m for m in warnings("dim", -3.0) if "clip" in m]


def test_a_diligent_name_without_its_image_is_said_not_dropped(base, tmp_path):
    """A typo in filenames.txt dropped its view without a word (the benchmark's subsets ship
    some of the 96 images, so an absent one is not an error): the capture now says which."""
    from captures import open_capture

    work = tmp_path / "w"
    shutil.copytree(base, work)
    edit(work / "dili" / "filenames.txt", "002.png", "0002.png")
    capture = open_capture(work / "dili", 1, "--downscale")
    assert [v.name for v in capture.views] == ["001"]
    assert any("1 of 2 images absent, left out: 0002.png (row 2)" in w for w in capture.warnings)


def test_gains_with_one_fitted_view_are_said_to_do_nothing(base, tmp_path, capsys, caplog):
    """fit.gains with a single fitted view: its gain is pinned at 1 by the gains' geometric
    mean, so the option did nothing, silently; now one warning names it and the way out. So
    does a phase's profile_gains given where no gain is fitted, and start_spread for one start."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    edit(work / "fit.toml", "uncertainty_spp = 4\n", 'uncertainty_spp = 4\ngains = "exposure"\n')
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 0, stderr
    said = " ".join(caplog.text.split())
    assert "fit.gains: with one fitted view its gain is pinned at 1" in said
    edit(work / "fit.toml", 'gains = "exposure"\n', "")
    edit(work / "fit.toml", "spp = 1\n", "spp = 1\nprofile_gains = true\n")
    caplog.clear()
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run2"], capsys)
    assert code == 0, stderr
    assert "fit.phases[0].profile_gains: no gains are fitted" in " ".join(caplog.text.split())
    edit(work / "fit.toml", "uncertainty_spp = 4\n", "uncertainty_spp = 4\nstart_spread = 2.0\n")
    caplog.clear()
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run3"], capsys)
    assert code == 0, stderr
    said = " ".join(caplog.text.split())
    assert "fit.start_spread: for a multi-start fit, and this one has one start" in said
    summary = json.loads((work / "run" / "summary.json").read_text())
    assert any("fit.gains" in w for w in summary["capture_warnings"])


def test_a_fit_of_many_pixels_is_warned_with_a_downscale(base, tmp_path, caplog, monkeypatch):
    """Three 6000x4000 photos fitted at full size (72 M pixels a step) were accepted without a
    word: 15 GB and no step in 6 minutes. Above `LARGE_PIXELS` a step, a
    warning gives the `fit.downscale` that renders about a million; below it, nothing."""
    import logging

    import fit.commands.prepare as fit_command
    from fit.config import load_fit_config

    cfg = load_fit_config(base / "fit.toml")
    with caplog.at_level(logging.WARNING):
        fit_command.prepare(cfg)
    assert not [r for r in caplog.records if "pixels a step" in r.getMessage()]
    caplog.clear()
    monkeypatch.setattr(fit_command, "LARGE_PIXELS", 100)
    with caplog.at_level(logging.WARNING):
        prepared = fit_command.prepare(cfg)
    (message,) = [r.getMessage() for r in caplog.records if "pixels a step" in r.getMessage()]
    views = prepared.problem.at(1).views
    pixels = sum(v.image.shape[0] * v.image.shape[1] for v in views)
    assert f"the fit renders {pixels:,} pixels a step" in message
    factor = cfg.downscale * math.ceil(math.sqrt(pixels / 1e6))
    assert f"set fit.downscale = {factor} (now {cfg.downscale}" in message
    assert message in prepared.capture.warnings  # in the summary and the report too
