"""Bad capture manifests, capture folders and DiLiGenT folders."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
from bad_inputs_cases import (
    GARBAGE,
    OBJ,
    Case,
    Setup,
    image,
    inspect_args,
    manifest,
    out,
    truncated_png,
    write,
)

from captures.images import write_image


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


def view_image(value: float) -> Setup:
    return image("cap/view_00.exr", value, (12, 16))


SPHERE = '[scene.geometry]\ntype = "sphere"\ncenter = [0.0, 0.0, 0.0]\nradius = 1.0'


CAPTURE_CASES: list[Case] = [
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
        "manifest-float-image-srgb",
        manifest('encoding = "linear"', 'encoding = "srgb"'),
        ("capture.toml", "views[0].image", 'encoding = "linear"'),
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
        "manifest-camera-width-zero",
        manifest("width = 16", "width = 0"),
        ("capture.toml", "views[0].camera.width = 0", "positive"),
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
]
