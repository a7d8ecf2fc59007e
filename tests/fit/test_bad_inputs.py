"""A corpus of bad inputs through `render`, `fit`, `synth` and `inspect`, run in-process through
`fit.entry.run`: each fails before any render with exit status 2 and one plain line naming the
file (or option), the field and the fix; nothing is written and every input stays byte-identical.
A few valid but unusual inputs succeed; Ctrl-C is one line and exit status 130."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from captures.images import write_image
from fit.entry import run as main

ROOT = Path(__file__).resolve().parents[2]

MATERIAL = '[material]\ntype = "glaze"\npigment = [0.3, 0.3, 0.3]\nroughness = 0.1\nior = 1.5\n'
FIT = f"""capture = "cap"
{MATERIAL}[fit]
free = ["glaze.roughness"]
uncertainty_spp = 4
[[fit.phases]]
solver = "adam"
steps = 1
spp = 1
"""

OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n"
SPHERE = '[scene.geometry]\ntype = "sphere"\ncenter = [0.0, 0.0, 0.0]\nradius = 1.0'


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A tiny valid project: a render config (16x12), its synthetic capture (one view, with
    [truth]), a fit config, a texture, an env map, a mesh, and a small DiLiGenT-style folder."""
    from fit.commands.synth import synthesize
    from fit.config import load_render_config
    from fit.material import save_preset

    root = tmp_path_factory.mktemp("base")
    text = (ROOT / "configs" / "glazed-sphere.toml").read_text()
    text = text.replace("width = 480", "width = 16").replace("height = 360", "height = 12")
    (root / "render.toml").write_text(text.replace("spp = 256", "spp = 2"))
    cfg = load_render_config(root / "render.toml")
    synthesize(cfg.scene, cfg.material, root / "cap", spp=2)
    save_preset(cfg.material, root / "preset.toml")
    (root / "fit.toml").write_text(FIT)
    write_image(root / "tex.png", np.full((4, 4, 3), 0.5, np.float32))
    write_image(root / "sky.exr", np.full((4, 8, 3), 0.1, np.float32))
    (root / "m.obj").write_text(OBJ)
    dili = root / "dili"
    dili.mkdir()
    yy, xx = np.mgrid[0:20, 0:24]
    disc = ((xx - 12) ** 2 + (yy - 10) ** 2 < 49).astype(np.float32)
    write_image(dili / "mask.png", np.repeat(disc[..., None], 3, -1))
    write_image(dili / "001.png", np.repeat(0.3 * disc[..., None] + 0.01, 3, -1))
    write_image(dili / "002.png", np.repeat(0.2 * disc[..., None] + 0.01, 3, -1))
    (dili / "filenames.txt").write_text("001.png\n002.png\n")
    (dili / "light_directions.txt").write_text("0.1 0.2 0.97\n-0.3 0.1 0.95\n")
    (dili / "light_intensities.txt").write_text("1.0 1.1 0.9\n0.8 1.0 1.2\n")
    return root


def edit(path: Path, old: str, new: str) -> None:
    """Replace the first `old` in a text file (which must hold it)."""
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def snapshot(folder: Path) -> dict[str, str]:
    """Every path under `folder` -> the SHA-256 of its bytes (folders: "dir")."""
    out = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        out[key] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def run(args: list, capsys) -> tuple[int, str, str]:
    """`layerfit ARGS` in this process: (exit status, stdout, stderr)."""
    with pytest.raises(SystemExit) as exit_:
        main([str(a) for a in args])
    out = capsys.readouterr()
    return exit_.value.code, out.out, out.err


# Cases: (id, mutate the work folder and return the arguments, substrings of the one error line)
Case = tuple[str, Callable[[Path], list], tuple[str, ...]]


Setup = Callable[[Path], object]


def out(rel: str) -> Callable[[Path], Path]:
    return lambda d: d / rel


def edited(rel: str, old: str, new: str, before: Setup | None = None) -> Setup:
    """A setup step: `before`, then `old` replaced by `new` in the file `rel` of the work folder."""

    def setup(d: Path) -> None:
        if before:
            before(d)
        edit(d / rel, old, new)

    return setup


def command(*args, setup: Setup | None = None) -> Callable[[Path], list]:
    """`setup`, then the arguments `args` (a callable one is called with the work folder)."""

    def make(d: Path) -> list:
        if setup:
            setup(d)
        return [a(d) if callable(a) else a for a in args]

    return make


def render_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("render", out("render.toml"), *extra, setup=setup)


def render_cfg(old: str, new: str, *extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return render_args("--out", out("o.png"), *extra, setup=edited("render.toml", old, new, setup))


def manifest(old: str, new: str, setup: Setup | None = None) -> Callable[[Path], list]:
    return inspect_args(
        out("cap"),
        "--no-silhouette",
        "--sheet",
        out("s.png"),
        setup=edited("cap/capture.toml", old, new, setup),
    )


def inspect_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("inspect", *extra, setup=setup)


def synth_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("synth", out("render.toml"), *extra, setup=setup)


def fit_args(*extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return command("fit", out("fit.toml"), *extra, setup=setup)


def fit_cfg(old: str, new: str, *extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return fit_args("--out", out("run"), *extra, setup=edited("fit.toml", old, new, setup))


def manifest_fit(old: str, new: str, free: str = "glaze.roughness") -> Callable[[Path], list]:
    """A fit of `free` alone, after `old` is replaced by `new` in the capture's manifest."""
    return fit_cfg(
        'free = ["glaze.roughness"]',
        f'free = ["{free}"]',
        setup=edited("cap/capture.toml", old, new),
    )


def dili(file: str, text: str | None):
    """A DiLiGenT folder with `file` replaced by `text` (None: removed)."""

    def make(d: Path) -> list:
        path = d / "dili" / file
        if text is None:
            path.unlink()
        else:
            path.write_text(text)
        return ["inspect", d / "dili", "--no-silhouette", "--sheet", d / "s.png"]

    return make


def write(rel: str, data: bytes | str | None = None, folder: bool = False):
    """A setup step: write a file (or make a folder) under the work folder."""

    def setup(d: Path) -> None:
        path = d / rel
        if folder:
            path.mkdir(parents=True)
        elif isinstance(data, bytes):
            path.write_bytes(data)
        else:
            path.write_text(data or "")

    return setup


def photographs(d: Path) -> None:
    """A copy of the capture as a user's photographs would be: no [truth] in its manifest."""
    shutil.copytree(d / "cap", d / "photos")
    manifest = d / "photos" / "capture.toml"
    text = manifest.read_text()
    assert "[truth]" in text
    manifest.write_text(text[: text.index("[truth]")])


def nan_checkpoint(d: Path) -> None:
    """A readable checkpoint whose vector is NaN (no fit saves one)."""
    (d / "run").mkdir()
    meta = np.array(json.dumps({"phase": 0, "step": 1, "history": [0.1]}))
    nan = np.full(1, np.nan, np.float32)
    with open(d / "run" / "checkpoint.npz", "wb") as f:
        np.savez(f, meta=meta, u=nan, u_phase=nan)


def image(rel: str, value: float, shape: tuple[int, int] = (4, 8)) -> Setup:
    """A setup step: an image of `shape` pixels, each `value`, written under the work folder."""
    return lambda d: write_image(d / rel, np.full((*shape, 3), value, np.float32))


def view_image(value: float) -> Setup:
    return image("cap/view_00.exr", value, (12, 16))


def obj_case(text: str | bytes, setup: Setup | None = None) -> Callable[[Path], list]:
    """A render of the config with its geometry the OBJ `text` (written as m.obj), after `setup`."""

    def write_obj(d: Path) -> None:
        if setup:
            setup(d)
        write("m.obj", text)(d)

    return render_cfg('geometry = "sphere"', 'geometry = "m.obj"', setup=write_obj)


def bad_obj(name: str, text: str | bytes, *expected: str, setup: Setup | None = None) -> Case:
    """The case `name`: a render of the OBJ `text`, whose error names m.obj and `expected`."""
    return name, obj_case(text, setup), ("m.obj", *expected)


def envmap(file: str, setup: Setup) -> Callable[[Path], list]:
    """A render lit by the environment map `file`, which `setup` writes."""
    return render_cfg(ENV, f'environment = {{type = "envmap", file = "{file}"}}', setup=setup)


def truncated_png(d: Path, shape=(4, 8)) -> bytes:
    """The first half of a valid noisy PNG's bytes (its header reads, its pixels do not)."""
    rng = np.random.default_rng(0)
    write_image(d / "whole.png", rng.random((*shape, 3)).astype(np.float32))
    data = (d / "whole.png").read_bytes()
    (d / "whole.png").unlink()
    return data[: len(data) // 2]


GARBAGE = b"\x89not an image at all\xff\xfe"
TEX = "pigment = [0.1, 0.22, 0.55]"
ENV = "environment = [0.05, 0.05, 0.06]"
RD = "[render]\nspp = 2"
FACE = "f 1/1 2/2 3/3"
NO_UVS = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"

CASES: list[Case] = [
    # --- render configs: file-level problems
    (
        "config-missing",
        lambda d: ["render", d / "nope.toml", "--out", d / "o.png"],
        ("nope.toml", "no such file"),
    ),
    (
        "config-is-folder",
        lambda d: ["render", d / "cap", "--out", d / "o.png"],
        ("cap", "is a folder"),
    ),
    (
        "config-not-utf8",
        lambda d: (
            (d / "render.toml").write_bytes(b"x = '\xff\xfe'\n")
            and ["render", d / "render.toml", "--out", d / "o.png"]
        ),
        ("render.toml", "not UTF-8"),
    ),
    ("config-bad-toml", render_cfg("[render]", "[render"), ("render.toml", "not valid TOML")),
    ("config-unknown-top", render_cfg(RD, RD + "\n[extra]\nx = 1"), ("render.toml", "extra")),
    (
        "material-unknown-key",
        render_cfg("ior = 1.52", "ior = 1.52\niorr = 2"),
        ("render.toml", "material.iorr"),
    ),
    ("material-ior-bounds", render_cfg("ior = 1.52", "ior = 9.0"), ("render.toml", "ior")),
    (
        "material-nan",
        render_cfg("roughness = 0.0625", "roughness = nan"),
        ("render.toml", "roughness"),
    ),
    ("render-spp-zero", render_cfg(RD, "[render]\nspp = 0"), ("render.toml", "render.spp")),
    (
        "render-spp-huge",  # was an internal error from Mitsuba's sample_count mid-render
        render_cfg(RD, "[render]\nspp = 99999999999999999999"),
        ("render.toml", "render.spp", "1048576"),
    ),
    ("camera-no-fov", render_cfg("fov_x_deg = 36.0", ""), ("render.toml", "fov_x_deg")),
    (
        "camera-target-origin",
        render_cfg("target = [0.0, 0.0, 0.0]", "target = [0.0, -5.0, 1.2]"),
        ("render.toml", "target"),
    ),
    (
        "light-inf",
        render_cfg("radiance = [200.0, 183.0, 163.0]", "radiance = [inf, 1.0, 1.0]"),
        ("render.toml", "radiance"),
    ),
    (
        "light-zero",
        render_cfg("radiance = [200.0, 183.0, 163.0]", "radiance = [0.0, 0.0, 0.0]"),
        ("render.toml", "lights"),
    ),
    (
        "env-negative",
        render_cfg(ENV, "environment = [-1.0, 0.05, 0.06]"),
        ("render.toml", "environment"),
    ),
    (
        "geometry-misspelt",
        render_cfg('geometry = "sphere"', 'geometry = "spehre"'),
        ("render.toml", "geometry", "sphere, cup"),
    ),
    (
        "obj-missing",
        render_cfg('geometry = "sphere"', 'geometry = "none.obj"'),
        ("render.toml", "geometry", "none.obj"),
    ),
    bad_obj("obj-out-of-range", OBJ.replace("3/3", "9/3"), "line 7", "range"),
    bad_obj("obj-vertex-two-numbers", OBJ.replace("v 0 0 0", "v 0 0"), "line 1", "2 numbers"),
    bad_obj("obj-vertex-nan", OBJ.replace("v 1 0 0", "v 1 0 nan"), "line 2", "not finite"),
    bad_obj("obj-relative-indices", OBJ.replace(FACE, "f -3/-3 -2/-2 -1/-1"), "line 7", "relative"),
    bad_obj("obj-zero-area", OBJ.replace("v 0 1 0", "v 2 0 0"), "zero area"),
    bad_obj(  # a plain glaze renders without UVs; its noise needs them
        "obj-no-uvs-noisy-glaze",
        NO_UVS,
        "texture coordinates",
        "glaze.pigment_noise",
        "unwrap",
        setup=edited("render.toml", 'type = "glaze"', 'type = "glaze"\npigment_noise = 0.2'),
    ),
    bad_obj(  # was painted per triangle (barycentric UVs), silently
        "obj-no-uvs-textured-pigment",
        NO_UVS,
        "texture coordinates",
        "glaze.pigment",
        "unwrap",
        setup=edited("render.toml", TEX, 'pigment = "tex.png"'),
    ),
    bad_obj("obj-garbage", GARBAGE, "not an OBJ text file"),
    (
        "obj-is-folder",
        render_cfg(
            'geometry = "sphere"', 'geometry = "dir.obj"', setup=write("dir.obj", folder=True)
        ),
        ("dir.obj", "folder"),
    ),
    bad_obj("obj-bad-index", OBJ.replace("3/3", "x/3"), "integer"),
    # the renderer's loader: "excessively long line" (an n-gon's face, a long comment)
    bad_obj(
        "obj-long-line",
        OBJ + "# " + "x" * 1100 + "\n",
        "line 8 is 1,102 characters long",
        "triangulate",
    ),
    # the renderer's loader: "could not parse line"
    bad_obj("obj-vt-one-number", OBJ.replace("vt 0 0", "vt 0"), "line 4", "takes 2 to 3"),
    # the renderer's loader: "invalid vertex normal data"
    bad_obj(
        "obj-zero-normal",
        OBJ.replace(FACE, "vn 0 0 0\nf 1/1/1 2/2/1 3/3/1"),
        "line 7",
        "'vn 0 0 0' has no direction",
        "face_normals = true",
    ),
    # rendered with uninitialised normals (1e21), black or lit at random, without a word
    bad_obj(
        "obj-normals-not-on-the-faces",
        OBJ.replace(FACE, "vn 0 0 1\n" + FACE),
        "3 of its 3 face corners name none",
        "face_normals = true",
    ),
    bad_obj(
        "obj-four-indices-a-corner",
        OBJ.replace(FACE, "vn 0 0 1\nf 1/1/1/1 2/2/1/1 3/3/1/1"),
        "line 8",
        "'1/1/1/1' has 4 indices",
    ),
    # the renderer skipped the marked first vertex: every face moved to the next ones
    bad_obj("obj-byte-order-mark", "\ufeff" + OBJ, "byte-order mark", "without BOM"),
    (
        "texture-garbage",
        render_cfg(TEX, 'pigment = "tex.png"', setup=write("tex.png", GARBAGE)),
        ("render.toml", "material.pigment", "tex.png"),
    ),
    (
        "texture-folder",
        render_cfg(TEX, 'pigment = "dir.png"', setup=write("dir.png", folder=True)),
        ("render.toml", "material.pigment"),
    ),
    ("texture-missing", render_cfg(TEX, 'pigment = "none.png"'), ("render.toml", "none.png")),
    (
        "texture-not-image-type",
        render_cfg(TEX, 'pigment = "tex.txt"', setup=write("tex.txt", "1")),
        ("render.toml", "tex.txt", "use .exr"),
    ),
    (
        "envmap-garbage",
        envmap("sky.exr", write("sky.exr", GARBAGE)),
        ("render.toml", "scene.environment.file", "sky.exr"),
    ),
    (
        "envmap-truncated",
        envmap("sky.png", lambda d: (d / "sky.png").write_bytes(truncated_png(d))),
        ("render.toml", "scene.environment.file", "sky.png", "truncated"),
    ),
    (
        "envmap-nan",
        envmap("sky.exr", image("sky.exr", np.nan)),
        ("render.toml", "scene.environment.file", "sky.exr", "not finite"),
    ),
    (
        "envmap-negative",  # rendered as negative light before
        envmap("sky.exr", image("sky.exr", -1.0)),
        ("render.toml", "scene.environment.file", "sky.exr", "negative radiance"),
    ),
    (
        "texture-pigment-above-one",  # a float image: a pigment of 3 rendered without a word
        render_cfg(TEX, 'pigment = "pig.exr"', setup=image("pig.exr", 3.0)),
        ("render.toml", "material.pigment", "pig.exr", "from 3 to 3", "[0.0, 1.0]", "rescale"),
    ),
    (
        "envmap-folder",
        envmap("dir.exr", write("dir.exr", folder=True)),
        ("render.toml", "scene.environment.file", "folder"),
    ),
    (
        "material-not-preset",
        render_cfg(
            '[material]\ntype = "glaze"', 'material = "nope.toml"\n[xmaterial]\ntype = "glaze"'
        ),
        ("render.toml", "xmaterial"),
    ),
    (
        "preset-newer-schema",
        lambda d: (
            (d / "p.toml").write_text('schema = 99\n[material]\ntype = "glaze"\n')
            and ["render", d / "p.toml", "--scene", d / "render.toml", "--out", d / "o.png"]
        ),
        ("p.toml", "schema = 99", "upgrade"),
    ),
    (
        "preset-without-scene",
        lambda d: (
            (d / "p.toml").write_text('schema = 1\n[material]\ntype = "glaze"\n')
            and ["render", d / "p.toml", "--out", d / "o.png"]
        ),
        ("p.toml", "--scene"),
    ),
    (
        "scene-file-no-scene",
        lambda d: (
            (d / "s.toml").write_text("x = 1\n")
            and ["render", d / "render.toml", "--scene", d / "s.toml", "--out", d / "o.png"]
        ),
        ("s.toml", "[scene]"),
    ),
    (  # "scene.cameras: missing; add it", which a manifest may not hold
        "scene-file-is-a-capture",
        lambda d: [
            "render",
            d / "render.toml",
            "--scene",
            d / "cap" / "capture.toml",
            "--out",
            d / "o.png",
        ],
        ("--scene", "capture.toml: is a capture manifest", "[[scene.cameras]]"),
    ),
    # --- render options and outputs
    ("render-spp-0", render_args("--spp", "0", "--out", out("o.png")), ("--spp",)),
    ("render-spp-neg", render_args("--spp", "-1", "--out", out("o.png")), ("--spp",)),
    ("render-seed-neg", render_args("--seed", "-3", "--out", out("o.png")), ("--seed",)),
    ("render-seed-huge", render_args("--seed", str(2**40), "--out", out("o.png")), ("--seed",)),
    (
        "render-spp-opt-huge",
        render_args("--spp", str(2**32 + 1), "--out", out("o.png")),
        ("--spp",),
    ),
    (
        "render-out-exists",
        render_args("--out", out("o.png"), setup=write("o.png", "precious")),
        ("--out", "o.png", "--force"),
    ),
    (
        "render-out-exr-exists",
        render_args("--out", out("o.png"), setup=write("o.exr", "x")),
        ("--out", "o.exr", "--force"),
    ),
    (
        "render-out-folder",
        render_args("--out", out("o.png"), setup=write("o.png", folder=True)),
        ("--out", "is a folder"),
    ),
    (
        "render-out-is-input",
        render_args(
            "--out",
            out("tex.png"),
            "--force",
            setup=lambda d: edit(d / "render.toml", TEX, 'pigment = "tex.png"'),
        ),
        ("--out", "tex.png", "input"),
    ),
    ("render-out-config", render_args("--out", out("render.toml")), ("--out", "render.toml")),
    ("render-out-suffix", render_args("--out", out("o.txt")), ("--out", "o.txt", "use .png")),
    (
        "render-out-parent-file",
        render_args("--out", out("f/o.png"), setup=write("f", "x")),
        ("--out", "is a file"),
    ),
    ("render-unknown-option", render_args("--sp", "3"), ("--sp",)),
    # --- synth options and outputs
    ("synth-exists", synth_args("--out", out("cap")), ("--out", "cap", "--force")),
    (  # synth wrote them, and inspect and fit then refused the capture
        "synth-camera-looks-away",
        synth_args(
            "--out",
            out("away"),
            setup=lambda d: edit(
                d / "render.toml", "target = [0.0, 0.0, 0.0]", "target = [0.0, -9.0, 1.2]"
            ),
        ),
        ("render.toml", "scene.cameras[0] does not see the object"),
    ),
    (
        "synth-camera-too-small",
        synth_args(
            "--out",
            out("tiny"),
            setup=lambda d: edit(d / "render.toml", "width = 16", "width = 3"),
        ),
        ("render.toml", "scene.cameras[0] is 3x12", "at least 4 pixels"),
    ),
    (
        "synth-force-not-capture",
        synth_args(
            "--out",
            out("other"),
            "--force",
            setup=lambda d: ((d / "other").mkdir(), (d / "other" / "keep.txt").write_text("x")),
        ),
        ("--out", "other", "capture.toml"),
    ),
    (
        "synth-out-file",
        synth_args("--out", out("f"), setup=write("f", "x")),
        ("--out", "is a file"),
    ),
    ("synth-out-holds-config", synth_args("--out", lambda d: d, "--force"), ("--out", "input")),
    (
        "synth-force-keeps-a-users-file",  # a note beside a synthetic capture's own files
        synth_args("--out", out("cap"), "--force", setup=write("cap/notes.txt", "x")),
        ("--out", "cap", "notes.txt", "synth did not write"),
    ),
    (
        "synth-force-photographs",  # a capture without [truth] holds a user's photographs
        synth_args("--out", out("photos"), "--force", setup=photographs),
        ("--out", "photos", "[truth]", "choose another path"),
    ),
    (
        "export-force-user-folder",
        lambda d: (
            (d / "mine").mkdir(),
            (d / "mine" / "thesis.txt").write_text("x"),
            ["export", d / "preset.toml", "--to", "usd", "--out", d / "mine", "--force"],
        )[-1],
        ("--out", "not a layerfit export", "thesis.txt", "choose another path"),
    ),
    (
        "synth-out-parent-file",
        synth_args("--out", out("f/c"), setup=write("f", "x")),
        ("--out", "is a file"),
    ),
    ("synth-shot-neg", synth_args("--out", out("c"), "--shot", "-1"), ("--shot",)),
    ("synth-read-neg", synth_args("--out", out("c"), "--read", "-0.5"), ("--read",)),
    (
        "synth-shot-nan",  # click's range check said "should be <= 1e6"
        synth_args("--out", out("c"), "--shot", "nan"),
        ("--shot", "not a finite number"),
    ),
    ("synth-ev-nan", synth_args("--out", out("c"), "--exposure-ev", "nan"), ("--exposure-ev",)),
    ("synth-ev-inf", synth_args("--out", out("c"), "--exposure-ev", "inf"), ("--exposure-ev",)),
    ("synth-ev-huge", synth_args("--out", out("c"), "--exposure-ev", "1e308"), ("--exposure-ev",)),
    (
        "synth-base-nan",
        synth_args("--out", out("c"), "--exposure-base", "nan"),
        ("--exposure-base",),
    ),
    ("synth-format", synth_args("--out", out("c"), "--format", "bmp"), ("--format", "exr")),
    ("synth-spp-0", synth_args("--out", out("c"), "--spp", "0"), ("--spp",)),
    ("synth-spp-huge", synth_args("--out", out("c"), "--spp", str(2**20 + 1)), ("--spp",)),
    ("synth-seed-neg", synth_args("--out", out("c"), "--seed", "-1"), ("--seed",)),
    ("synth-no-out", synth_args(), ("--out",)),
    # --- inspect options and outputs
    (
        "inspect-downscale-0",
        inspect_args(out("cap"), "--downscale", "0", "--sheet", out("s.png")),
        ("--downscale",),
    ),
    ("inspect-downscale-neg", inspect_args(out("cap"), "--downscale", "-2"), ("--downscale",)),
    ("bench-only", lambda d: ["bench", "--only", "speed"], ("--only", "profile or versus")),
    ("bench-spp-huge", lambda d: ["bench", "--spp", "100000"], ("--spp",)),
    ("bench-size", lambda d: ["bench", "--only", "recovery", "--size", "3x3"], ("--size",)),
    ("bench-size-text", lambda d: ["bench", "--only", "grid", "--size", "big"], ("--size",)),
    ("bench-shapes", lambda d: ["bench", "--only", "recovery", "--shapes", "cube"], ("--shapes",)),
    ("bench-widths", lambda d: ["bench", "--only", "grid", "--widths", "64,x"], ("--widths",)),
    (
        "bench-fit-free",
        lambda d: (
            edit(d / "fit.toml", 'free = ["glaze.roughness"]', 'free = ["glaze.nope"]')
            or ["bench", "--only", "fit", "--fit-config", d / "fit.toml"]
        ),
        ("fit.toml", "fit.free", "glaze.nope"),
    ),
    (
        "bench-results-folder",
        lambda d: ["bench", "--only", "recovery", "--results", d],
        ("--results", "folder"),
    ),
    (
        "inspect-sheet-manifest",
        inspect_args(out("cap"), "--sheet", out("cap/capture.toml")),
        ("--sheet", "capture.toml", "capture folder"),
    ),
    (
        "inspect-sheet-image",
        inspect_args(out("cap"), "--sheet", out("cap/view_00.png"), "--force"),
        ("--sheet", "capture folder"),
    ),
    (
        "inspect-sheet-exists",
        inspect_args(out("cap"), "--sheet", out("s.png"), setup=write("s.png", "precious")),
        ("--sheet", "s.png", "--force"),
    ),
    (
        "inspect-sheet-folder",
        inspect_args(out("cap"), "--sheet", out("s.png"), setup=write("s.png", folder=True)),
        ("--sheet", "is a folder"),
    ),
    (
        "inspect-sheet-suffix",
        inspect_args(out("cap"), "--sheet", out("s.txt")),
        ("--sheet", "s.txt", ".png"),
    ),
    (
        "inspect-sheet-parent-file",
        inspect_args(out("cap"), "--sheet", out("f/s.png"), setup=write("f", "x")),
        ("--sheet", "is a file"),
    ),
    (
        "capture-is-image",
        inspect_args(out("cap/view_00.exr"), "--sheet", out("s.png")),
        ("view_00.exr", "not a capture"),
    ),
    (
        "capture-missing",
        inspect_args(out("nope"), "--sheet", out("s.png")),
        ("nope", "no such capture"),
    ),
    (
        "capture-empty-folder",
        inspect_args(out("empty"), "--sheet", out("s.png"), setup=write("empty", folder=True)),
        ("empty", "capture.toml"),
    ),
    # --- capture manifests
    (
        "manifest-no-views",
        inspect_args(
            out("cap"),
            "--sheet",
            out("s.png"),
            setup=lambda d: (d / "cap" / "capture.toml").write_text(
                (d / "cap" / "capture.toml").read_text().split("[[views]]")[0]
            ),
        ),
        ("capture.toml", "views", "[[views]]"),
    ),
    (
        "manifest-unknown-key",
        manifest('encoding = "linear"', 'encoding = "linear"\nfoo = 1'),
        ("capture.toml", "capture.foo"),
    ),
    (
        "manifest-encoding",
        manifest('encoding = "linear"', 'encoding = "log"'),
        ("capture.toml", "capture.encoding"),
    ),
    (
        "manifest-downscale-0",
        manifest('encoding = "linear"', 'encoding = "linear"\ndownscale = 0'),
        ("capture.toml", "capture.downscale"),
    ),
    (
        "manifest-white-balance",
        manifest('encoding = "linear"', 'encoding = "linear"\nwhite_balance = "camera"'),
        ("capture.toml", "white_balance"),
    ),
    (
        "manifest-ev-huge",
        manifest("exposure_ev = 0.0", "exposure_ev = 5000.0"),
        ("capture.toml", "views[0].exposure_ev"),
    ),
    (
        "manifest-ev-nan",
        manifest("exposure_ev = 0.0", "exposure_ev = nan"),
        ("capture.toml", "views[0].exposure_ev"),
    ),
    (
        "manifest-gain-zero",
        manifest("exposure_ev = 0.0", "gain = 0.0"),
        ("capture.toml", "views[0].gain"),
    ),
    (
        "manifest-gain-tiny",
        manifest("exposure_ev = 0.0", "gain = 1e-300"),
        ("capture.toml", "views[0].gain"),
    ),
    (
        "manifest-gain-and-ev",
        manifest("exposure_ev = 0.0", "exposure_ev = 0.0\ngain = 1.0"),
        ("capture.toml", "views[0].gain"),
    ),
    (
        "manifest-image-number",
        manifest('image = "view_00.exr"', "image = 1"),
        ("capture.toml", "views[0].image", "got 1; should be a file name (a string)"),
    ),
    (
        "manifest-image-missing",
        manifest('image = "view_00.exr"', 'image = "none.exr"'),
        ("capture.toml", "views[0].image", "none.exr"),
    ),
    (
        "manifest-image-outside",
        manifest('image = "view_00.exr"', 'image = "../sky.exr"'),
        ("capture.toml", "views[0].image", "outside"),
    ),
    (
        "manifest-image-garbage",
        manifest('image = "view_00.exr"', 'image = "g.exr"', setup=write("cap/g.exr", GARBAGE)),
        ("g.exr", "not an image"),
    ),
    (
        "manifest-image-folder",
        manifest(
            'image = "view_00.exr"', 'image = "dir.exr"', setup=write("cap/dir.exr", folder=True)
        ),
        ("dir.exr",),
    ),
    (
        "manifest-image-65504",
        manifest("exposure_ev = 0.0", "exposure_ev = 0.0", setup=view_image(65504.0)),
        ("capture.toml", "views[0].image", "saturated"),
    ),
    (
        "manifest-image-black",
        manifest("exposure_ev = 0.0", "exposure_ev = 0.0", setup=view_image(0.0)),
        ("capture.toml", "views[0].image", "no valid pixel"),
    ),
    (
        "manifest-mask-size",
        manifest(
            'image = "view_00.exr"',
            'image = "view_00.exr"\nmask = "m.png"',
            setup=lambda d: write_image(d / "cap" / "m.png", np.ones((3, 3, 3))),
        ),
        ("capture.toml", "views[0].mask"),
    ),
    (
        "manifest-camera-size",
        manifest("width = 16", "width = 17"),
        ("capture.toml", "views[0].camera"),
    ),
    (
        "manifest-camera-width-string",
        manifest("width = 16", 'width = "16"'),
        ("capture.toml", "views[0].camera.width"),
    ),
    (
        "manifest-camera-fov-string",
        manifest("fov_x_deg = 36.0", 'fov_x_deg = "wide"'),
        ("capture.toml", "views[0].camera.fov_x_deg"),
    ),
    (
        "manifest-camera-up-along-view",
        manifest("up = [0.0, 0.0, 1.0]", "up = [0.0, 5.0, -1.2]"),
        ("capture.toml", "views[0].camera.up", "viewing direction"),
    ),
    (
        "manifest-camera-up-zero",
        manifest("up = [0.0, 0.0, 1.0]", "up = [0.0, 0.0, 0.0]"),
        ("capture.toml", "views[0].camera.up"),
    ),
    (
        "manifest-two-views-one-name",
        manifest(
            "[truth]",
            '[[views]]\nimage = "sub/view_00.exr"\n[views.camera]\norigin = [0.0, 5.0, 1.2]\n'
            "target = [0.0, 0.0, 0.0]\nfov_x_deg = 36.0\n\n[truth]",
            setup=lambda d: (
                (d / "cap" / "sub").mkdir(),
                shutil.copy(d / "cap" / "view_00.exr", d / "cap" / "sub"),
            ),
        ),
        ("capture.toml", "views[1].image", "rename"),
    ),
    (
        "manifest-dilate-huge",
        manifest('encoding = "linear"', 'encoding = "linear"\ndilate = 100000'),
        ("capture.toml", "dilate"),
    ),
    (
        "manifest-view-truncated",
        manifest(
            'image = "view_00.exr"',
            'image = "t.png"',
            setup=lambda d: (d / "cap" / "t.png").write_bytes(truncated_png(d, (12, 16))),
        ),
        ("capture.toml", "views[0].image", "t.png", "truncated"),
    ),
    (
        "manifest-scene-cameras",
        manifest("max_depth = 8", "max_depth = 8\ncameras = []"),
        ("capture.toml", "scene.cameras"),
    ),
    (
        "manifest-camera-away",
        manifest("target = [0.0, 0.0, 0.0]", "target = [0.0, -9.0, 1.2]"),
        ("capture.toml", "views[0].camera", "does not see"),
    ),
    (
        "manifest-not-utf8",
        inspect_args(
            out("cap"), "--sheet", out("s.png"), setup=write("cap/capture.toml", b"\xff\xfe")
        ),
        ("capture.toml", "UTF-8"),
    ),
    (
        "manifest-is-folder",
        inspect_args(
            out("cap"),
            "--sheet",
            out("s.png"),
            setup=lambda d: (
                (d / "cap" / "capture.toml").unlink(),
                (d / "cap" / "capture.toml").mkdir(),
            ),
        ),
        ("capture.toml", "folder"),
    ),
    (
        "truth-nan-in-list",
        manifest("[0.1, 0.22, 0.55]", "[0.1, nan, 0.55]"),
        ("capture.toml", "truth.glaze.pigment[1]", "finite"),
    ),
    (
        "truth-inf",
        manifest('"glaze.ior" = 1.52', '"glaze.ior" = inf'),
        ("capture.toml", "truth.glaze.ior", "finite"),
    ),
    (
        "truth-text",
        manifest('"glaze.ior" = 1.52', '"glaze.ior" = "high"'),
        ("capture.toml", "truth.glaze.ior"),
    ),
    (
        "obj-outside-capture",
        manifest(SPHERE, '[scene.geometry]\ntype = "obj"\nfile = "../m.obj"'),
        ("capture.toml", "scene.geometry", "outside the capture folder"),
    ),
    (
        "envmap-outside-capture",
        manifest(
            'type = "constant"\nradiance = [0.05, 0.05, 0.06]',
            'type = "envmap"\nfile = "../sky.exr"',
        ),
        ("capture.toml", "scene.environment.file", "outside the capture folder"),
    ),
    (
        "obj-out-of-range-capture",
        manifest(
            SPHERE,
            '[scene.geometry]\ntype = "obj"\nfile = "m.obj"',
            setup=write("cap/m.obj", OBJ.replace("2/2", "7/2")),
        ),
        ("m.obj", "out of range"),
    ),
    # --- DiLiGenT folders
    (
        "dili-no-intensities",
        dili("light_intensities.txt", None),
        ("light_intensities.txt", "missing"),
    ),
    ("dili-no-directions", dili("light_directions.txt", None), ("light_directions.txt",)),
    (
        "dili-non-numeric",
        dili("light_directions.txt", "a b c\n0 0 1\n"),
        ("light_directions.txt", "row 1", "three numbers"),
    ),
    (
        "dili-two-columns",
        dili("light_intensities.txt", "1 1\n1 1 1\n"),
        ("light_intensities.txt", "row 1"),
    ),
    (
        "dili-zero-intensity",
        dili("light_intensities.txt", "0 0 0\n1 1 1\n"),
        ("light_intensities.txt", "row 1", "> 0"),
    ),
    (
        "dili-negative-intensity",
        dili("light_intensities.txt", "1 1 1\n1 -1 1\n"),
        ("light_intensities.txt", "row 2", "> 0"),
    ),
    (
        "dili-name-twice",
        dili("filenames.txt", "001.png\n001.png\n"),
        ("filenames.txt", "row 2 (001.png) repeats row 1"),
    ),
    (
        "dili-name-outside",
        dili("filenames.txt", "001.png\n../cap/view_00.png\n"),
        ("filenames.txt", "row 2", "outside the folder"),
    ),
    (
        "dili-zero-direction",
        dili("light_directions.txt", "0 0 0\n0 0 1\n"),
        ("light_directions.txt", "row 1", "zero"),
    ),
    (
        "dili-nan-direction",
        dili("light_directions.txt", "nan 0 1\n0 0 1\n"),
        ("light_directions.txt", "row 1", "finite"),
    ),
    (
        "dili-count-mismatch",
        dili("light_directions.txt", "0 0 1\n"),
        ("filenames.txt", "light_directions.txt", "one row per image"),
    ),
    (
        "dili-empty-mask",
        inspect_args(
            out("dili"), "--sheet", out("s.png"), setup=image("dili/mask.png", 0.0, (20, 24))
        ),
        ("mask.png", "fewer than 10"),
    ),
    # --- fit configs
    (
        "fit-capture-missing",
        fit_cfg('capture = "cap"', 'capture = "none"'),
        ("fit.toml", "capture", "does not exist"),
    ),
    (
        "fit-capture-image",
        fit_cfg('capture = "cap"', 'capture = "cap/view_00.exr"'),
        ("view_00.exr", "not a capture"),
    ),
    (
        "fit-free-unknown",
        fit_cfg('free = ["glaze.roughness"]', 'free = ["glaze.rough"]'),
        ("fit.toml", "fit.free", "glaze.rough"),
    ),
    (
        "fit-free-disabled-layer",
        fit_cfg(
            MATERIAL,
            '[material]\ntype = "layered"\n[[material.layers]]\n'
            'name = "clay"\ntype = "oren_nayar"\n[[material.layers]]\nname = "glaze"\n'
            'type = "glaze"\nenabled = false\n[material.layers.mask]\nthreshold = 0.3\n',
        ),
        ("fit.toml", "fit.free", "'glaze'", "clay"),
    ),
    (
        "fit-truth-wrong-length",
        manifest_fit('"glaze.roughness" = 0.0625', '"glaze.roughness" = [0.0625, 0.1]'),
        ("capture.toml", "truth.glaze.roughness"),
    ),
    (
        "fit-truth-out-of-bounds",  # scored, it read as the fit's error (-7.66)
        manifest_fit('"glaze.ior" = 1.52', '"glaze.ior" = 9.0', "glaze.ior"),
        ("capture.toml", "truth.glaze.ior", "outside its bounds [1.01, 3.0]"),
    ),
    (
        "fit-truth-scalar-for-rgb",
        manifest_fit(
            '"glaze.pigment" = [0.1, 0.22, 0.55]', '"glaze.pigment" = 0.2', "glaze.pigment"
        ),
        ("capture.toml", "truth.glaze.pigment", "3 numbers"),
    ),
    (
        "fit-truth-options-bad-choice",
        manifest_fit('"glaze.diffuse" = "qualitative"', '"glaze.diffuse" = "x"'),
        ("capture.toml", "truth_options.glaze.diffuse", "qualitative, eon"),
    ),
    (
        "fit-truth-options-unknown-option",
        manifest_fit('"glaze.diffuse" = "qualitative"', '"glaze.lobe" = "eon"'),
        ("capture.toml", "truth_options.glaze.lobe", "diffuse"),
    ),
    (
        "fit-free-twice",
        fit_cfg('free = ["glaze.roughness"]', 'free = ["glaze.roughness", "glaze.roughness"]'),
        ("fit.toml", "fit.free", "more than once"),
    ),
    (
        "fit-spp-huge",
        fit_cfg("spp = 1\n", "spp = 100000000\n"),
        ("fit.toml", "phases[0]", "1048576"),
    ),
    (
        "fit-starts-spp-huge",  # the starts' common loss: one render at full resolution
        fit_cfg("[fit]\n", "[fit]\nstarts = 2\nstarts_spp = 100000000\n"),
        ("fit.toml", "fit.starts_spp", "1048576"),
    ),
    (
        "fit-seed-huge",  # was an OverflowError (int32) at the first step
        fit_cfg("[fit]\n", "[fit]\nseed = 4294967296\n"),
        ("fit.toml", "fit.seed", "4294967295"),
    ),
    (
        "fit-seed-huger",  # was an OverflowError (C long)
        fit_cfg("[fit]\n", "[fit]\nseed = 99999999999999999999\n"),
        ("fit.toml", "fit.seed", "4294967295"),
    ),
    (
        "batch-out-under-file",  # was an internal error (NotADirectoryError) once Ray had started
        lambda d: (
            (d / "f").write_text("x"),
            (d / "batch.toml").write_text('configs = ["fit.toml"]\nout = "f/b"\n'),
            ["batch", d / "batch.toml"],
        )[-1],
        ("batch.toml", "out = 'f/b'", "is a file, not a folder"),
    ),
    (
        "fit-uncertainty-spp-huge",
        fit_cfg("uncertainty_spp = 4", "uncertainty_spp = 100000000"),
        ("fit.toml", "uncertainty_spp", "1048576"),
    ),
    (
        "fit-loss-scale-with-l2",
        fit_cfg("uncertainty_spp = 4\n", "uncertainty_spp = 4\nloss_scale = 0.1\n"),
        ("fit.toml", "fit.loss_scale", "huber"),
    ),
    (
        "fit-phase-primal-spp-huge",
        fit_cfg('solver = "adam"\n', 'solver = "gn"\nprimal_spp = 2000000\n'),
        ("fit.toml", "fit.phases[0].primal_spp:", "1048576"),
    ),
    (
        "fit-phase-hold-string",
        fit_cfg("spp = 1\n", 'spp = 1\nhold = "glaze.ior"\n'),
        ("fit.toml", "fit.phases[0].hold", "should be an array"),
    ),
    (
        "fit-phase-steps-bool",
        fit_cfg("steps = 1\n", "steps = true\n"),
        ("fit.toml", "fit.phases[0].steps", "integer"),
    ),
    (
        "fit-phase-spp-string",
        fit_cfg("spp = 1\n", 'spp = "1"\n'),
        ("fit.toml", "fit.phases[0].spp", "integer"),
    ),
    (
        "fit-phase-steps-float",
        fit_cfg("steps = 1\n", "steps = 1.0\n"),
        ("fit.toml", "fit.phases[0].steps", "integer"),
    ),
    (
        "fit-phase-lr-string",
        fit_cfg("spp = 1\n", 'spp = 1\nlr = "0.1"\n'),
        ("fit.toml", "fit.phases[0].lr", "'0.1'", "number"),
    ),
    (
        "fit-phase-downscale-huge",
        fit_cfg("spp = 1\n", "spp = 1\ndownscale = 4\n"),
        ("fit.toml", "fit.phases[0].downscale", "4 pixels"),
    ),
    (
        "fit-resume-corrupt-checkpoint",
        fit_args(
            "--out",
            out("run"),
            "--resume",
            setup=lambda d: ((d / "run").mkdir(), (d / "run" / "checkpoint.npz").write_bytes(b"")),
        ),
        ("checkpoint.npz", "unreadable"),
    ),
    (
        "fit-resume-nan-checkpoint",
        fit_args("--out", out("run"), "--resume", setup=nan_checkpoint),
        ("checkpoint.npz", "non-finite", "without --resume"),
    ),
    (
        "manifest-downscale-huge",
        fit_args(
            "--out",
            out("run"),
            setup=lambda d: edit(
                d / "cap" / "capture.toml", "[capture]\n", "[capture]\ndownscale = 1000\n"
            ),
        ),
        ("capture.toml", "capture.downscale = 1000", "smaller factor"),
    ),
    (
        "inspect-downscale-huge",
        inspect_args(out("cap"), "--downscale", "8", "--sheet", out("s.png")),
        ("--downscale = 8", "4 pixels", "smaller factor"),
    ),
    (
        "fit-variant-unknown",  # refused before the run folder (or its parent) is made
        fit_args("--out", out("new/run"), "--variant", "bogus_rgb"),
        ("--variant", "bogus_rgb", "llvm_ad_rgb"),
    ),
    (
        "fit-variant-scalar",
        fit_args("--out", out("run"), "--variant", "scalar_rgb"),
        ("--variant", "scalar_rgb", "llvm_ad_rgb"),
    ),
    (
        "manifest-float-image-srgb",
        manifest('encoding = "linear"', 'encoding = "srgb"'),
        ("capture.toml", "views[0].image", 'encoding = "linear"'),
    ),
    (  # was an internal error at the first render ("not in the scene ... nothing to fit")
        "fit-free-environment-scale-without-one",
        manifest_fit("[0.05, 0.05, 0.06]", "[0, 0, 0]", "environment.scale"),
        ("fit.toml", "fit.free: environment.scale", "no environment", "drop the key"),
    ),
    (
        "fit-free-gains",
        fit_cfg('free = ["glaze.roughness"]', 'free = ["gains"]'),
        ("fit.toml", "fit.free", "fit.gains"),
    ),
    (
        "fit-material-missing-preset",
        fit_cfg(MATERIAL, 'material = "nope.toml"\n'),
        ("fit.toml", "nope.toml", "no such preset file"),
    ),
    (
        "fit-capture-self",
        fit_cfg('capture = "cap"', 'capture = "fit.toml"'),
        ("fit.toml", "capture"),
    ),
    (
        "fit-capture-empty",
        fit_cfg('capture = "cap"', 'capture = ""'),
        ("fit.toml", "capture", "empty"),
    ),
    (
        "fit-capture-is-a-config",
        fit_cfg('capture = "cap"', 'capture = "render.toml"'),
        ("render.toml", "not a capture manifest"),
    ),
    (
        "fit-capture-is-a-preset",
        fit_cfg('capture = "cap"', 'capture = "preset.toml"'),
        ("preset.toml", "is a preset, not a capture manifest"),
    ),
    ("synth-fit-config", lambda d: ["synth", d / "fit.toml", "--out", d / "c"], ("fit config",)),
    (
        "export-fit-config",
        lambda d: ["export", d / "fit.toml", "--to", "usd", "--out", d / "e"],
        ("fit.toml", "is a fit config, not a preset"),
    ),
    (
        "manifest-camera-width-zero",
        manifest("width = 16", "width = 0"),
        ("capture.toml", "views[0].camera.width = 0", "positive"),
    ),
    (
        "light-temperature-zero",
        render_cfg("radiance = [200.0, 183.0, 163.0]", "radiance = 200.0\ntemperature = 0"),
        ("render.toml", "temperature", "1667"),
    ),
    (
        "bench-out-is-results",
        lambda d: ["bench", "--only", "versus", "--results", d / "r.json", "--out", d / "r.json"],
        ("--out", "r.json", "input"),
    ),
    (
        "bench-out-is-plot",
        lambda d: ["bench", "--only", "grid", "--results", d / "g.json", "--out", d / "v.png"],
        ("--out", "v.png", ".md"),
    ),
    (
        "bench-plot-is-users",
        lambda d: (
            (d / "mine.png").write_text("the user's own"),
            ["bench", "--only", "versus", "--results", d / "r3.json", "--out", d / "mine.md"],
        )[-1],
        ("mine.png", "--force"),
    ),
    (
        "bench-results-under-file",
        lambda d: (
            (d / "f").write_text("x"),
            ["bench", "--only", "recovery", "--results", d / "f" / "x.json"],
        )[-1],
        ("--results", "is a file"),
    ),
    (
        "fit-render-config",
        lambda d: ["fit", d / "render.toml", "--out", d / "run"],
        ("render.toml", "not a fit config"),
    ),
    ("fit-holdout-all", fit_args("--out", out("run"), "--holdout", "1"), ("holdout",)),
    ("fit-holdout-neg", fit_args("--out", out("run"), "--holdout", "-1"), ("--holdout",)),
    ("fit-out-file", fit_args("--out", out("f"), setup=write("f", "x")), ("--out", "is a file")),
    (
        "fit-out-parent-file",
        fit_args("--out", out("f/run"), setup=write("f", "x")),
        ("--out", "cannot write"),
    ),
    (
        "fit-out-not-empty",
        fit_args(
            "--out",
            out("run"),
            setup=lambda d: ((d / "run").mkdir(), (d / "run" / "keep.txt").write_text("x")),
        ),
        ("--out", "--force"),
    ),
    (
        "fit-force-not-a-run",
        fit_args(
            "--out",
            out("run"),
            "--force",
            setup=lambda d: ((d / "run").mkdir(), (d / "run" / "my_photo.exr").write_text("x")),
        ),
        ("--out", "no layerfit run"),
    ),
    (  # a run's entries of the other kind: an internal error, or a refusal, after the whole fit
        "fit-force-report-is-a-file",
        fit_args(
            "--out",
            out("run"),
            "--force",
            setup=lambda d: (
                (d / "run").mkdir(),
                (d / "run" / "summary.json").write_text("{}"),
                (d / "run" / "report").write_text("x"),
            ),
        ),
        ("--out", "report is a file, where the run writes its report"),
    ),
    (
        "fit-force-preset-is-a-folder",
        fit_args(
            "--out",
            out("run"),
            "--force",
            setup=lambda d: (
                (d / "run" / "preset.toml").mkdir(parents=True),
                (d / "run" / "summary.json").write_text("{}"),
            ),
        ),
        ("--out", "preset.toml is a folder"),
    ),
    ("fit-out-holds-inputs", fit_args("--out", lambda d: d, "--force"), ("--out", "inputs")),
    ("fit-resume-nothing", fit_args("--out", out("run"), "--resume"), ("--resume", "checkpoint")),
    ("fit-steps-zero", fit_cfg("steps = 1", "steps = 0"), ("fit.toml", "fit.phases[0].steps")),
    (  # blamed the phase's factor, 1 (its own check after the capture's)
        "fit-downscale-huge",
        fit_cfg("[fit]\n", "[fit]\ndownscale = 100\n"),
        ("fit.toml: fit.downscale = 100 leaves view", "smaller factor"),
    ),
    (
        "fit-downscale-zero",
        fit_cfg("[fit]\n", "[fit]\ndownscale = 0\n"),
        ("fit.toml", "fit.downscale"),
    ),
    ("fit-loss", fit_cfg("[fit]\n", '[fit]\nloss = "l3"\n'), ("fit.toml", "fit.loss")),
    ("fit-gains", fit_cfg("[fit]\n", '[fit]\ngains = "rgb"\n'), ("fit.toml", "fit.gains")),
    ("fit-solver", fit_cfg('solver = "adam"', 'solver = "newton"'), ("fit.toml", "solver")),
    (
        "fit-hold-unknown",
        fit_cfg("spp = 1\n", 'spp = 1\nhold = ["*.threshold"]\n'),
        ("fit.toml", "fit.phases[0].hold", "'*.threshold'", "glaze.roughness"),
    ),
    ("fit-no-free", fit_cfg('free = ["glaze.roughness"]', "free = []"), ("fit.toml", "fit.free")),
    (
        "fit-not-utf8",
        lambda d: (
            (d / "fit.toml").write_bytes(b"capture = '\xff'\n")
            and ["fit", d / "fit.toml", "--out", d / "run"]
        ),
        ("fit.toml", "UTF-8"),
    ),
    ("fit-config-folder", lambda d: ["fit", d / "cap", "--out", d / "run"], ("cap", "folder")),
]


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


@contextlib.contextmanager
def without_root() -> Iterator[None]:
    """Inside, this process acts as the user `nobody` where it runs as root (root writes into a
    read-only folder: CI runs as root); elsewhere nothing changes."""
    if os.geteuid() != 0:
        yield
        return
    import pwd

    nobody = pwd.getpwnam("nobody")
    os.setegid(nobody.pw_gid)
    os.seteuid(nobody.pw_uid)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


@pytest.mark.parametrize(
    "make",
    [
        render_args("--out", out("ro/o.png")),
        synth_args("--out", out("ro/c")),
        inspect_args(out("cap"), "--no-silhouette", "--sheet", out("ro/s.png")),
        fit_args("--out", out("ro/run")),
    ],
    ids=["render", "synth", "inspect", "fit"],
)
def test_read_only_output_folder(base, capsys, make):
    import tempfile

    import fit.commands.fit  # every module the commands import on the way (read as root)
    import fit.commands.inspect
    import fit.commands.render
    import fit.commands.synth  # noqa: F401

    # a folder `nobody` may read (pytest's own are its owner's alone), its `ro` read-only
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder) / "w"
        shutil.copytree(base, work)
        for path in [Path(folder), work, *work.rglob("*")]:
            path.chmod(0o755 if path.is_dir() else 0o644)
        (work / "ro").mkdir()
        (work / "ro").chmod(0o555)
        try:
            with without_root():
                assert not os.access(work / "ro", os.W_OK, effective_ids=True)  # as it tests
                code, _, stderr = run(make(work), capsys)
        finally:
            (work / "ro").chmod(0o755)
        assert code == 2 and len(stderr.strip().splitlines()) == 1 and "ro" in stderr, stderr
        assert "cannot write" in stderr or "Permission denied" in stderr, stderr
        assert not any((work / "ro").iterdir())


def test_corpus_is_large_and_ids_unique():
    assert len(CASES) >= 80 and len({c[0] for c in CASES}) == len(CASES)


def test_help_shows_bracketed_text(capsys):
    code, stdout, _ = run(["synth", "--help"], capsys)
    assert code == 0 and "[truth]" in stdout and "[scene]" in stdout
    code, stdout, _ = run(["fit", "--help"], capsys)
    assert code == 0 and "capture, material, fit" in stdout


# Valid but unusual inputs ------------------------------------------------------------------------


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


# Ctrl-C -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_ctrl_c_in_synth_is_one_line_and_leaves_nothing(base, tmp_path, capsys, monkeypatch, how):
    """Ctrl-C, or SIGTERM (a kill), while the views render: nothing is left behind."""
    import os
    import signal

    import fit.render

    def interrupted(*args, **kwargs):
        if how == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)  # the CLI's handler raises KeyboardInterrupt
            raise AssertionError("SIGTERM did not stop the render")
        raise KeyboardInterrupt

    monkeypatch.setattr(fit.render, "render", interrupted)
    work = tmp_path / "w"
    shutil.copytree(base, work)
    before = snapshot(work)
    code, _, stderr = run(["synth", work / "render.toml", "--out", work / "c"], capsys)
    lines = [line for line in stderr.splitlines() if line.strip().startswith(("error", "Trace"))]
    assert code == 130 and not lines and "interrupted: nothing written" in stderr, stderr
    assert snapshot(work) == before  # no capture, no hidden temporary folder


def test_ctrl_c_in_fit_is_one_line_exit_130(base, tmp_path, capsys, monkeypatch):
    import fit.commands.fit as fit_command

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_command, "run_schedule", interrupted)
    work = tmp_path / "w"
    shutil.copytree(base, work)
    code, _, stderr = run(["fit", work / "fit.toml", "--out", work / "run"], capsys)
    assert code == 130 and "Traceback" not in stderr, stderr
    assert [line for line in stderr.splitlines() if "interrupted" in line] == [
        "interrupted: nothing to resume (stopped before the first checkpoint)"
    ]
    assert not [p for p in work.rglob("*") if ".partial" in p.name]


# Warnings -----------------------------------------------------------------------------------------


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


def test_cuda_without_a_device_is_one_line(base, tmp_path, capsys):
    """`--variant cuda_ad_rgb` where there is no CUDA device: one line saying so, exit 2,
    nothing made (was an internal error from Dr.Jit at the first render)."""
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA device")
    work = tmp_path / "w"
    shutil.copytree(base, work)
    before = snapshot(work)
    args = ["fit", work / "fit.toml", "--out", work / "a" / "run", "--variant", "cuda_ad_rgb"]
    code, stdout, stderr = run(args, capsys)
    assert code == 2 and not stdout and "no usable CUDA device" in stderr, stderr
    assert stderr.count("\n") == 1
    assert snapshot(work) == before


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


def test_a_name_too_long_for_the_file_system_is_one_line(tmp_path, capsys):
    """An output path with a name over 255 bytes: one line naming the path and the fix, exit 2
    (it was "internal error (OSError: [Errno 36] File name too long)"), nothing written."""
    long = tmp_path / ("x" * 300)
    code, _, stderr = run(
        ["synth", str(ROOT / "configs" / "glazed-sphere.toml"), "--out", str(long)], capsys
    )
    assert code == 2 and "longer than the file system allows" in stderr and "x" * 300 in stderr
    assert list(tmp_path.iterdir()) == []


def test_a_layer_named_alone_in_free_says_to_name_its_parameters():
    """free = ["glaze"] said "no layer '' is built (built: glaze)"."""
    from fit.material import resolve
    from fit.material.build import build_material

    material = build_material({"type": "glaze"})
    with pytest.raises(KeyError, match=r"'glaze' is a layer; name its parameters: glaze\.pigment"):
        resolve(material, ["glaze"])


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


def test_a_ctrl_c_while_the_command_line_is_built_is_one_line(capsys, monkeypatch):
    """A Ctrl-C inside typer's building of the command (before click's own handling): it left a
    traceback and a death by SIGINT (seen in CI, 1 s into a fit); now one line, exit 130."""
    import fit.entry as entry

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(entry, "_command", interrupted)
    code, _, stderr = run(["fit", "x.toml"], capsys)
    assert code == 130 and stderr.strip() == "interrupted: stopped by Ctrl-C or SIGTERM"


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
