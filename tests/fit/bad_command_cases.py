"""Bad render configs, meshes, textures and environment maps, and bad options of the commands."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bad_inputs_cases import (
    GARBAGE,
    OBJ,
    Case,
    Setup,
    edit,
    edited,
    image,
    inspect_args,
    out,
    render_args,
    render_cfg,
    synth_args,
    truncated_png,
    write,
)


def photographs(d: Path) -> None:
    """A copy of the capture as a user's photographs would be: no [truth] in its manifest."""
    shutil.copytree(d / "cap", d / "photos")
    manifest = d / "photos" / "capture.toml"
    text = manifest.read_text()
    assert "[truth]" in text
    manifest.write_text(text[: text.index("[truth]")])


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


TEX = "pigment = [0.1, 0.22, 0.55]"


ENV = "environment = [0.05, 0.05, 0.06]"


RD = "[render]\nspp = 2"


FACE = "f 1/1 2/2 3/3"


NO_UVS = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


COMMAND_CASES: list[Case] = [
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
        "light-temperature-zero",
        render_cfg("radiance = [200.0, 183.0, 163.0]", "radiance = 200.0\ntemperature = 0"),
        ("render.toml", "temperature", "1667"),
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
        "export-fit-config",
        lambda d: ["export", d / "fit.toml", "--to", "usd", "--out", d / "e"],
        ("fit.toml", "is a fit config, not a preset"),
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
    ("synth-fit-config", lambda d: ["synth", d / "fit.toml", "--out", d / "c"], ("fit config",)),
    # --- inspect options and outputs
    (
        "inspect-downscale-0",
        inspect_args(out("cap"), "--downscale", "0", "--sheet", out("s.png")),
        ("--downscale",),
    ),
    ("inspect-downscale-neg", inspect_args(out("cap"), "--downscale", "-2"), ("--downscale",)),
    (
        "inspect-downscale-huge",
        inspect_args(out("cap"), "--downscale", "8", "--sheet", out("s.png")),
        ("--downscale = 8", "4 pixels", "smaller factor"),
    ),
    ("bench-only", lambda d: ["bench", "--only", "speed"], ("--only", "quality or texture-step")),
    ("bench-spp-huge", lambda d: ["bench", "--spp", "100000"], ("--spp",)),
    ("bench-size", lambda d: ["bench", "--only", "recovery", "--size", "3x3"], ("--size",)),
    ("bench-size-text", lambda d: ["bench", "--only", "grid", "--size", "big"], ("--size",)),
    ("bench-shapes", lambda d: ["bench", "--only", "recovery", "--shapes", "cube"], ("--shapes",)),
    ("bench-cases", lambda d: ["bench", "--only", "recovery", "--cases", "alpha 7"], ("--cases",)),
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
]
