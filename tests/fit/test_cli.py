"""`layerfit render` and config validation: outputs whole, errors that name file and key."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli

from captures import InputError
from captures.images import read_image, srgb_decode
from fit.config import load_render_config

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ROOT / "configs" / "glazed-sphere.toml"


def small_config(tmp_path: Path, **material) -> Path:
    """The bundled config at 64x48 and 16 spp, with material overrides."""
    text = (
        DEFAULT.read_text()
        .replace("width = 480", "width = 64")
        .replace("height = 360", "height = 48")
    )
    text = text.replace("spp = 256", "spp = 16")
    for key, value in material.items():
        text = text.replace("[material]\n", f"[material]\n{key} = {value}\n", 1)
    path = tmp_path / "small.toml"
    path.write_text(text)
    return path


def test_bundled_config_loads():
    cfg = load_render_config(DEFAULT)
    assert cfg.material.bsdf["type"] == "glaze" and cfg.material.bsdf["roughness"] == 0.0625
    assert len(cfg.scene.cameras) == 1 and len(cfg.scene.lights) == 2


def test_render_writes_exr_and_png(tmp_path):
    out = run_cli("render", small_config(tmp_path), "--out", tmp_path / "img.png")
    assert out.returncode == 0, out.stderr
    exr, png = read_image(tmp_path / "img.exr"), read_image(tmp_path / "img.png")
    assert exr.shape == (48, 64, 3) and png.shape == (48, 64, 3)
    assert np.all(np.isfinite(exr)) and exr.max() > 0.1
    # the PNG is the EXR, sRGB-encoded and clipped, to 16-bit precision
    np.testing.assert_allclose(srgb_decode(png), np.clip(exr, 0, 1), atol=2e-4)
    # the blue pigment shows: more blue than red on the object
    centre = exr[18:30, 26:38]
    assert centre[..., 2].mean() > 1.5 * centre[..., 0].mean()
    # an upper-case .EXR is that EXR, written once (it wrote b.exr and b.EXR, the same image)
    (tmp_path / "upper").mkdir()
    out = run_cli("render", small_config(tmp_path), "--out", tmp_path / "upper" / "b.EXR")
    assert out.returncode == 0, out.stderr
    assert [p.name for p in (tmp_path / "upper").iterdir()] == ["b.EXR"]


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            ("[material]\n", "[material]\nroughnes = 0.2\n"),
            "material.roughnes: unknown key for glaze",
        ),
        (("ior = 1.52", "ior = 0.9"), "material: ior = 0.9 is outside its bounds [1.01, 3.0]"),
        (('fresnel = "schlick"', 'fresnel = "fast"'), "material: fresnel = 'fast'; choose one of"),
        (("fov_x_deg = 36.0", "fov = 36.0"), "scene.cameras[0].fov: unknown key"),
        (("spp = 256", "spp = 0"), "render.spp: got 0; should be greater than"),
        (
            ('geometry = "sphere"', 'geometry = "cup.obj"'),
            "scene.geometry.file: 'cup.obj' does not exist",
        ),
        (("[render]", "[rendr]"), "rendr: unknown key"),
    ],
)
def test_config_errors_name_file_and_key(tmp_path, edit, message):
    text = DEFAULT.read_text()
    assert edit[0] in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(InputError) as err:  # ConfigError for [material], [render]
        load_render_config(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_cli_bad_config_writes_nothing(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(DEFAULT.read_text().replace("ior = 1.52", "ior = 7"))
    out = run_cli("render", path, "--out", tmp_path / "img.png")
    assert out.returncode == 2
    assert f"{path}: material: ior = 7" in out.stderr
    assert not list(tmp_path.glob("img*"))


def test_missing_and_invalid_files(tmp_path):
    with pytest.raises(InputError, match=r"none\.toml: no such file"):
        load_render_config(tmp_path / "none.toml")
    (tmp_path / "broken.toml").write_text("[scene\n")
    with pytest.raises(InputError, match=r"broken\.toml: not valid TOML"):
        load_render_config(tmp_path / "broken.toml")


def test_bench_table_runs():
    """The benchmark command's table is complete (its timings are reported, never asserted)."""
    from fit.bench import bsdf_speed_table

    table = bsdf_speed_table(spp=1, repeats=1)
    assert [row[0] for row in table.rows][:2] == ["principled", "glaze paper/schlick"]
    assert all(float(row[1]) > 0 for row in table.rows)
    assert "| glaze paper/exact |" in table.markdown()


def test_render_a_preset_in_a_scene(tmp_path):
    """`layerfit render PRESET --scene SCENE.toml`: a preset is usable wherever a material is;
    without --scene it says what is missing."""
    from fit.material import save_preset

    material = load_render_config(DEFAULT).material
    preset = save_preset(material.with_values({"glaze.roughness": 0.3}), tmp_path / "p.toml")
    out = run_cli("render", preset, "--scene", DEFAULT, "--spp", 1, "--out", tmp_path / "r.png")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "r.exr").exists() and (tmp_path / "r.png").exists()
    missing = run_cli("render", preset, "--out", tmp_path / "s.png")
    assert missing.returncode == 2 and "give --scene" in missing.stderr


def test_a_malformed_results_file_is_one_line(tmp_path):
    """A resumable results file with the right setting but malformed entries is refused naming
    the entry and the fix (was an AttributeError or a KeyError after the setting matched)."""
    import json

    import pytest

    from captures.errors import InputError
    from fit.bench import resumed

    setting = {"size": [8, 6]}
    path = tmp_path / "r.json"
    for entries, message in (
        ("oops", r"runs: not a table of finished entries"),
        ({"tutorial 0": {"max_relative_error": 0.1}}, r"runs\['tutorial 0'\]: no seconds"),
        ({"tutorial 0": [1, 2]}, r"runs\['tutorial 0'\]: no seconds"),
    ):
        path.write_text(json.dumps({"setting": setting, "runs": entries}))
        with pytest.raises(InputError, match=message):
            resumed(path, setting, "runs", "another setting", False)
    path.write_text(json.dumps({"setting": setting, "runs": {"a": {"seconds": 1.0}}}))
    assert resumed(path, setting, "runs", "another setting", False) == {"a": {"seconds": 1.0}}


def test_bench_tables_name_the_cpu_family_and_vector_unit():
    """Two VMs both called "AMD EPYC" ran the same fits 4x apart (AVX-512 or not): a table's
    machine line says the first processor's family, model and widest vector unit, and falls
    back to the model name alone, or the platform's, where /proc/cpuinfo has less."""
    from fit.bench import machine

    two = (
        "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel\t\t: 2\n"
        "model name\t: AMD EPYC\nflags\t\t: fpu sse4_2 avx avx2 avx512f\n\n"
        "processor\t: 1\ncpu family\t: 25\nmodel\t\t: 1\nmodel name\t: Other\nflags\t\t: avx\n"
    )
    assert machine(two).startswith("AMD EPYC (family 26, model 2, AVX-512), ")
    intel = "model name\t: Intel Xeon\ncpu family\t: 6\nmodel\t\t: 85\nflags\t\t: sse4_2 avx2\n"
    assert machine(intel).startswith("Intel Xeon (family 6, model 85, AVX2), ")
    assert machine("\nmodel name\t: Bare CPU\n").startswith("Bare CPU, ")
    assert " cores, " in machine("") and "mitsuba " in machine("")


@pytest.mark.parametrize(
    "code, status, said",
    [(None, 0, ""), (0, 0, ""), (3, 3, ""), ("stopped: why", 1, "stopped: why\n")],
)
def test_the_entry_exits_after_its_handlers_with_its_status(code, status, said):
    """`layerfit` ends without the interpreter's teardown (`fit.entry._exit`): the exit handlers
    run first, what was printed is flushed, a numeric status is kept, none is 0, and a message
    is printed with status 1 (as Python's own exit does)."""
    script = (
        "import atexit, sys; from fit.entry import _exit; "
        "atexit.register(lambda: print(' handled', end='')); "
        f"print('written', end=''); sys.stderr.write('e'); _exit({code!r})"
    )
    command = [sys.executable, "-c", script]
    done = subprocess.run(command, check=False, capture_output=True, text=True)
    assert done.returncode == status
    assert done.stdout == "written handled" and done.stderr == "e" + said
