"""Valid but unusual inputs succeed: no UVs, dotted names, the largest seed, odd cameras, NaN sd."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from bad_inputs_cases import FIT, edit, run


def test_a_mesh_without_uvs_renders_a_plain_glaze(base, tmp_path, capsys):
    """A scanned mesh rarely has UVs: a material that looks nothing up in UV space renders (and
    fits) on it; only masks, textures and the glaze's noise need them."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    (work / "m.obj").write_text("v -1 -1 0\nv 1 -1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")
    edit(work / "render.toml", 'geometry = "sphere"', 'geometry = "m.obj"')
    code, _, stderr = run(["render", work / "render.toml", "--out", work / "o.png"], capsys)
    assert code == 0, stderr
    code, _, stderr = run(["synth", work / "render.toml", "--out", work / "c"], capsys)
    assert code == 0, stderr
    edit(work / "fit.toml", 'capture = "cap"', 'capture = "c"')
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 0, stderr


def test_render_keeps_every_dot_of_the_out_name(base, tmp_path, capsys):
    """`--out shot.v2.png` writes shot.v2.png and shot.v2.exr; a `shot.png` beside it (a name the
    user never gave) is left alone, even with --force (was: cut at the first dot, overwritten)."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    (work / "shot.png").write_text("the user's own")
    args = ["render", work / "render.toml", "--out", work / "shot.v2.png", "--spp", "1"]
    code, _, stderr = run([*args, "--force"], capsys)
    assert code == 0, stderr
    assert (work / "shot.v2.png").is_file() and (work / "shot.v2.exr").is_file()
    assert (work / "shot.png").read_text() == "the user's own"
    assert not (work / "shot.exr").exists()


def test_the_largest_seed_renders_more_than_one_pass(base, tmp_path, capsys):
    """--seed 2^32 - 1 with two passes: the second pass's seed wraps (was an internal error)."""
    from fit.render.image import PASS_SPP

    args = ["render", base / "render.toml", "--out", tmp_path / "o.png"]
    code, _, stderr = run([*args, "--seed", str(2**32 - 1), "--spp", str(PASS_SPP + 1)], capsys)
    assert code == 0, stderr


def test_the_largest_seed_synthesizes_two_views(base, tmp_path, capsys):
    """synth --seed 2^32 - 1 with two cameras: the second view's seed (+1000) wraps (was an
    internal error from Mitsuba's sampler)."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    text = (work / "render.toml").read_text()
    camera = text[text.index("[[scene.cameras]]") :].split("\n\n")[0]
    edit(work / "render.toml", camera, f"{camera}\n\n{camera}")
    args = ["synth", work / "render.toml", "--out", work / "c", "--spp", "1"]
    code, _, stderr = run([*args, "--seed", str(2**32 - 1)], capsys)
    assert code == 0, stderr
    assert (work / "c" / "view_01.exr").is_file()


def test_the_largest_seed_fits_with_every_solver(base, tmp_path, capsys):
    """fit.seed = 2^32 - 1 (a batch's `seeds` reach the fit the same way) through every solver
    with gains: the phases' seeds (seed + k), the steps' (seed * 100003 + i + 1) and their offsets
    pass int32 and wrap modulo 2^32, as the renderer takes seeds (was an OverflowError from
    fit.seed = 21475 on)."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    phases = "".join(
        f'\n[[fit.phases]]\nsolver = "{solver}"\nsteps = 1\nspp = 2\n{extra}'
        for solver, extra in (
            ("adam", ""),
            ("gn", "jacobian_spp = 2\nrefresh = 1\n"),
            ("lm", "jacobian_spp = 2\n"),
            ("bfgs", ""),
        )
    )
    text = FIT.split("[[fit.phases]]")[0].replace("[fit]\n", "[fit]\nseed = 4294967295\n")
    (work / "fit.toml").write_text(text + "gains = true\n" + phases)
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 0, stderr
    assert json.loads((work / "run" / "summary.json").read_text())["seed"] == 2**32 - 1


def test_an_uncertainty_that_is_not_finite_leaves_its_parameters_undetermined():
    """A curvature with a non-finite row, or all of it NaN (the Jacobian of a render at a
    diverged fit's extreme values), leaves those coordinates undetermined (was LinAlgError from
    eigh: the whole fit lost); a residual that is not finite is no observation, a derivative
    that is not finite no information on its parameter (the others keep theirs)."""
    from fit.solvers.uncertainty import finite_rows, inverse_determined

    inverse, undetermined = inverse_determined(np.full((3, 3), np.nan))
    assert undetermined.all() and not inverse.any()
    h = np.diag([2.0, 4.0, 1.0])
    h[0, 2] = h[2, 0] = np.inf
    inverse, undetermined = inverse_determined(h)
    assert undetermined.tolist() == [True, False, True]
    assert np.allclose(inverse, np.diag([0.0, 0.25, 0.0]))
    r, jac = np.array([1.0, np.nan, 2.0]), np.array([[1.0, 2.0], [3.0, 4.0], [np.inf, 5.0]])
    r, jac = finite_rows(r, jac)
    assert r.tolist() == [1.0, 0.0, 2.0] and jac.tolist() == [[1.0, 2.0], [0.0, 0.0], [0.0, 5.0]]


def test_a_fit_whose_uncertainty_renders_nan_is_written(base, tmp_path, capsys, monkeypatch):
    """The uncertainty's Jacobian renders all NaN (as after Adam at lr = 100): the fit's run
    folder is written, the parameter reported undetermined (was an internal error after every
    step had run, only the checkpoint left)."""
    import importlib

    module = importlib.import_module("fit.solvers.uncertainty")  # the package exports a function
    real = module.linearised

    def nan(*args, **kwargs):
        r, jac = real(*args, **kwargs)
        return r, np.full_like(jac, np.nan)

    monkeypatch.setattr(module, "linearised", nan)
    work = tmp_path / "w"
    shutil.copytree(base, work)
    free = '["glaze.pigment", "glaze.roughness"]'  # more than one: eigh of a 1x1 NaN passed
    edit(work / "fit.toml", '["glaze.roughness"]', free)
    code, stdout, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 0, stderr
    summary = json.loads((work / "run" / "summary.json").read_text())
    # infinite (undetermined) standard deviations are null in the JSON
    assert summary["std"] == {"glaze.pigment": [None] * 3, "glaze.roughness": None}
    assert summary["poorly_determined"] == ["glaze.pigment", "glaze.roughness"]
    assert (work / "run" / "preset.toml").is_file() and "inf" in stdout


def test_the_reports_error_over_sd_is_blank_where_the_sd_is_undetermined_or_zero():
    """An undetermined (infinite) sd showed error/sd "+0" in the report and the row was never
    marked off; a zero sd gave the summary 1e28. Both are now no ratio."""
    from fit.output.report import _parameter_rows

    summary = {
        "values": {"a": 0.5, "b": [0.1, 0.2, 0.3]},
        "start": {"a": 0.4, "b": [0.1, 0.1, 0.1]},
        "std": {"a": float("inf"), "b": [float("inf"), 0.01, 0.0]},
        "truth": {"a": 0.4, "b": [0.0, 0.1, 0.2]},
        "error": {"a": 0.1, "b": [0.1, 0.1, 0.1]},
    }
    rows = {cells[0]: cells for _, cells in _parameter_rows(summary)}
    (a,) = [c for k, c in rows.items() if ">a<" in k]
    (b,) = [c for k, c in rows.items() if ">b<" in k]
    assert "+0" not in a[-1] and "+10" in b[-1] and "+0," not in b[-1]


def test_unusual_cameras_render(base, tmp_path, capsys):
    """An orthographic camera at an odd size and a thin lens render."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    edit(
        work / "render.toml",
        "fov_x_deg = 36.0\nwidth = 16\nheight = 12",
        'type = "orthographic"\northo_width = 3.0\nwidth = 7\nheight = 5\n\n'
        "[[scene.cameras]]\norigin = [0.0, -5.0, 1.2]\ntarget = [0.0, 0.0, 0.0]\n"
        "fov_x_deg = 30.0\nwidth = 9\nheight = 3\naperture_radius = 0.05",
    )
    code, _, stderr = run(["render", work / "render.toml", "--out", work / "o.png"], capsys)
    assert code == 0, stderr
    from captures.images import read_image

    assert read_image(work / "o_00.exr").shape == (5, 7, 3)
    assert read_image(work / "o_01.png").shape == (3, 9, 3)
    # again: refused without --force, replaced with it
    assert run(["render", work / "render.toml", "--out", work / "o.png"], capsys)[0] == 2
    code, _, stderr = run(
        ["render", work / "render.toml", "--out", work / "o.png", "--force", "--spp", "1"], capsys
    )
    assert code == 0, stderr


def test_one_view_fit_writes_valid_json(base, tmp_path, capsys):
    """A one-view capture fits; summary.json is strict JSON (no NaN or Infinity)."""
    work = tmp_path / "w"
    shutil.copytree(base, work)
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 0, stderr

    def refuse(name):
        raise ValueError(f"summary.json holds {name}")

    summary = json.loads((work / "run" / "summary.json").read_text(), parse_constant=refuse)
    assert summary["truth"]["glaze.roughness"] == 0.0625
    # --force over it: what the earlier run wrote and this one does not is gone, the user's own
    # files stay (an image too), nothing of this run is missing
    (work / "run" / "report" / "view-07-gone.png").write_bytes(b"old")  # the old report's:
    with open(work / "run" / "report.html", "a") as page:
        page.write("<img src='report/view-07-gone.png' alt='view 07'>")
    (work / "run" / "report" / "my-notes.png").write_bytes(b"mine")  # the user's, shown nowhere
    (work / "run" / "glaze.mask.texture.exr").write_bytes(b"old")  # as if fitted back then
    summary["values"]["glaze.mask.texture"] = 0.5
    (work / "run" / "summary.json").write_text(json.dumps(summary))
    (work / "run" / "notes.txt").write_text("mine")
    (work / "run" / "my_photo.exr").write_bytes(b"mine")
    (work / "run" / "preset.glaze.old.png").write_bytes(b"old")  # a texture its preset named
    (work / "run" / "my-pigment.png").write_bytes(b"mine")  # a hand-edited preset's texture
    with open(work / "run" / "preset.toml", "a") as preset:
        preset.write('\n[extra]\ntexture = "preset.glaze.old.png"\nmine = "my-pigment.png"\n')
    written = sorted(p.name for p in (work / "run").rglob("*"))
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run", "--force"], capsys)
    assert code == 0, stderr
    assert not (work / "run" / "report" / "view-07-gone.png").exists()
    assert not (work / "run" / "glaze.mask.texture.exr").exists()
    assert not (work / "run" / "preset.glaze.old.png").exists()
    assert (work / "run" / "notes.txt").read_text() == "mine"
    assert (work / "run" / "my_photo.exr").read_bytes() == b"mine"
    assert (work / "run" / "report" / "my-notes.png").read_bytes() == b"mine"
    assert (work / "run" / "my-pigment.png").read_bytes() == b"mine"
    gone = ("view-07-gone.png", "glaze.mask.texture.exr", "preset.glaze.old.png")
    expected = [n for n in written if n not in gone]
    assert sorted(p.name for p in (work / "run").rglob("*")) == expected


def test_synth_force_replaces_a_capture_and_inspect_odd_downscale(base, tmp_path, capsys):
    work = tmp_path / "w"
    shutil.copytree(base, work)
    (work / "cap" / "notes.txt").write_text("mine")  # not synth's: --force would delete it
    args = ["synth", work / "render.toml", "--out", work / "cap", "--spp", "1", "--force"]
    code, _, stderr = run(args, capsys)
    assert code == 2 and "notes.txt, which synth did not write" in stderr, stderr
    assert (work / "cap" / "notes.txt").read_text() == "mine"
    (work / "cap" / "notes.txt").unlink()
    old = {p.name for p in (work / "cap").iterdir()}
    code, _, stderr = run(args, capsys)
    assert code == 0, stderr
    assert {p.name for p in (work / "cap").iterdir()} == old  # the capture, replaced whole
    assert not [p for p in work.iterdir() if p.name.startswith(".")]  # no temporary folder left
    args = ["inspect", work / "cap", "--no-silhouette", "--downscale", "3", "--sheet"]
    code, _, stderr = run([*args, work / "s.png"], capsys)
    assert code == 0 and (work / "s.png").exists(), stderr
    code, _, stderr = run(
        ["inspect", work / "dili", "--no-silhouette", "--sheet", work / "d.png"], capsys
    )
    assert code == 0, stderr


def test_a_disabled_layer_keeps_the_other_layers_keys(tmp_path):
    """Disabling one of two layers leaves `clay.sigma` (not `oren_nayar.sigma`), and a free key
    of the disabled layer names that layer."""
    from fit.material import build_material, resolve

    table = {
        "type": "layered",
        "layers": [
            {"name": "clay", "type": "oren_nayar", "sigma": 0.2},
            {"name": "glaze", "type": "glaze", "enabled": False, "mask": {"threshold": 0.3}},
        ],
    }
    material = build_material(table, tmp_path / "m.toml")
    assert "clay.sigma" in material.params and "oren_nayar.sigma" not in material.params
    assert [f.key for f in resolve(material, ["clay.sigma"])] == ["clay.sigma"]
    with pytest.raises(KeyError, match="no layer 'glaze' is built"):
        resolve(material, ["glaze.roughness"])


def test_manifest_downscale_is_applied(base):
    """fit.downscale (through open_capture) and [capture] downscale both reach a manifest."""
    from captures import open_capture

    assert open_capture(base / "cap", 2).views[0].image.shape == (6, 8, 3)
    assert open_capture(base / "cap", 2).views[0].camera.width == 8
