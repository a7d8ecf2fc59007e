"""Bad fit configs, fit options and run folders, checkpoints and batch configs."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bad_inputs_cases import (
    MATERIAL,
    Case,
    Setup,
    edit,
    edited,
    fit_args,
    out,
    write,
)


def fit_cfg(old: str, new: str, *extra, setup: Setup | None = None) -> Callable[[Path], list]:
    return fit_args("--out", out("run"), *extra, setup=edited("fit.toml", old, new, setup))


def manifest_fit(old: str, new: str, free: str = "glaze.roughness") -> Callable[[Path], list]:
    """A fit of `free` alone, after `old` is replaced by `new` in the capture's manifest."""
    return fit_cfg(
        'free = ["glaze.roughness"]',
        f'free = ["{free}"]',
        setup=edited("cap/capture.toml", old, new),
    )


def nan_checkpoint(d: Path) -> None:
    """A readable checkpoint whose vector is NaN (no fit saves one)."""
    (d / "run").mkdir()
    meta = np.array(json.dumps({"phase": 0, "step": 1, "history": [0.1]}))
    nan = np.full(1, np.nan, np.float32)
    with open(d / "run" / "checkpoint.npz", "wb") as f:
        np.savez(f, meta=meta, u=nan, u_phase=nan)


FIT_CASES: list[Case] = [
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
        "fit-truth-texture-missing",
        manifest_fit(
            '"glaze.diffuse" = "qualitative"',
            '"glaze.diffuse" = "qualitative"\n[truth_textures]\n"glaze.mask.texture" = "gone.exr"',
        ),
        ("capture.toml", "truth_textures.glaze.mask.texture", "does not exist"),
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
        "fit-phase-relaxed-minima-crossed",
        fit_cfg('solver = "adam"\n', 'solver = "gn"\nrelaxed = true\nrelaxed_min = 10\n'),
        ("fit.toml", "fit.phases[0].relaxed_min_determined", "above relaxed_min = 10"),
    ),
    (
        "fit-phase-spp-limit-below-spp",
        fit_cfg('solver = "adam"\n', 'solver = "gn"\nspp_limit = 1\n'),
        ("fit.toml", "fit.phases[0].spp_limit", "does not raise spp = 1"),
    ),
    (
        "fit-phase-shared-paths-with-primal-spp",
        fit_cfg('solver = "adam"\n', 'solver = "gn"\nprimal_spp = 4\nshared_paths = true\n'),
        ("fit.toml", "fit.phases[0].shared_paths", "remove primal_spp = 4"),
    ),
    (
        "fit-phase-shared-paths-reverse-gradient",
        fit_cfg('solver = "adam"\n', 'solver = "gn"\ngradient = "reverse"\nshared_paths = true\n'),
        ("fit.toml", "fit.phases[0].shared_paths", 'set gradient = "control"'),
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
        "fit-variant-unknown",  # refused before the run folder (or its parent) is made
        fit_args("--out", out("new/run"), "--variant", "bogus_rgb"),
        ("--variant", "bogus_rgb", "llvm_ad_rgb"),
    ),
    (
        "fit-variant-scalar",
        fit_args("--out", out("run"), "--variant", "scalar_rgb"),
        ("--variant", "scalar_rgb", "llvm_ad_rgb"),
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
