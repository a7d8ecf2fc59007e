"""A mask's texels get an sd (`texel_sd`): each texel's own information, from the curvature's
probes (two reverse passes through the layer choice's Russian roulette), at most the sd of a value
uniform over [0, 1] where no pixel sees the texel."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from captures.capture import Capture, View
from captures.images import write_image
from fit.config import load_render_config
from fit.material import build_material, resolve
from fit.material.textures import with_free_textures
from fit.render import load_scene, render, scene_dict
from fit.solvers import Phase, Problem, run_schedule
from fit.solvers.textures import curvature, residual_scale, texel_sd

ROOT = Path(__file__).resolve().parents[2]
#: The painted mask (height, width): the glaze over the upper half of the UV square (the view
#: sees half of each row).
MASK = np.array([[1.0] * 4, [1.0] * 4, [0.0] * 4, [0.0] * 4])[..., None]
UNIFORM = 1.0 / np.sqrt(12.0)


def stack(tmp_path: Path, mask: str | None):
    """Dark red clay under a blue glaze whose share is the painted mask (none: a flat 0.5; no
    fbm grain)."""
    painted = {"texture": mask} if mask else {}
    return build_material(
        {
            "type": "layered",
            "layers": [
                {"name": "clay", "type": "oren_nayar", "reflectance": [0.5, 0.15, 0.1]},
                {
                    "name": "glaze",
                    "type": "glaze",
                    "pigment": [0.1, 0.22, 0.55],
                    "roughness": 0.2,
                    "ior": 1.5,
                    "mask": {**painted, "threshold": 0.0, "softness": 0.005},
                },
            ],
        },
        tmp_path / "m.toml",
    )


def mask_problem(tmp_path: Path, width: int = 12, height: int = 12):
    """The glazed sphere's first view, small, of the stack above; the mask a free 4x4 texture
    beside the glaze's ior from a flat start; the solver's vector at the start."""
    write_image(tmp_path / "mask.exr", MASK.astype(np.float32))
    truth = stack(tmp_path, "mask.exr")
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=width, height=height)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    image = render(load_scene(scene_dict(scene, truth, 0, 64)), 512, seed=5)
    capture = Capture(scene, [View("v", image, np.ones((height, width), np.float32), camera)])
    material = with_free_textures(stack(tmp_path, None), {"glaze.mask.texture": (4, 4)})
    problem = Problem(capture, material, resolve(material, ["glaze.mask.texture", "glaze.ior"]))
    return problem, problem.unconstrained({f.key: f.start for f in problem.free})


def test_a_mask_texels_curvature_matches_its_rendered_jacobian(tmp_path):
    """The probes' diagonal (`curvature`) against the mask's Jacobian rendered row by row (one
    reverse pass per pixel channel): `sum_p J_pi^2` per texel, where texels are seen; 0 where no
    pixel sees one (the sphere's far side)."""
    problem, u = mask_problem(tmp_path)
    values = problem.values(u)
    start = values["glaze.mask.texture"]
    assert np.allclose(start, 0.5)  # a flat start (a free mask without its file's texels)
    x = np.append(np.ravel(start), values["glaze.ior"]).astype(np.float32)
    renderer = problem.renderer(1)
    scale = residual_scale(problem, u)
    rows = {seed: [] for seed in (100, 1000)}  # two independent renders: their product unbiased
    for seed, row in rows.items():
        for p in range(scale.size):
            cotangent = np.zeros(scale.size, np.float32)
            cotangent[p] = scale[p]
            row.append(renderer.vjp(x, seed + p, 256, cotangent)[:16].astype(np.float64))
    expected = np.sum(np.multiply(*(np.asarray(r) for r in rows.values())), axis=0)
    h = np.mean([curvature(problem, u, 64, seed)[:16] for seed in range(1, 33)], axis=0)
    seen = expected > 0.05 * expected.max()
    assert 3 <= seen.sum() <= 12, expected
    assert np.all(h[expected == 0] == 0)
    # the probes' mean over 32 seeds against the rows' sum: measured 0.86-1.26 of it (0.61-1.34
    # over 8 seeds: the probes' own noise, not a bias)
    np.testing.assert_allclose(h[seen], expected[seen], rtol=0.35)

    std, share = texel_sd(problem, u, h, 1e-4, {"glaze.mask.texture"})
    sd = std["glaze.mask.texture"]
    assert sd.shape == (4, 4, 1) and share["glaze.mask.texture"] == np.mean(h > 0)
    np.testing.assert_allclose(sd.ravel()[seen], np.sqrt(1e-4 / h[seen]), rtol=1e-5)
    assert np.allclose(sd.ravel()[h == 0], UNIFORM)
    assert np.all(sd <= UNIFORM + 1e-7)


def test_a_stop_asked_for_ends_the_curvature_before_its_renders(tmp_path):
    """A Ctrl-C while the masks' curvature renders stops it before the next probe."""
    problem, u = mask_problem(tmp_path, 4, 4)
    with pytest.raises(KeyboardInterrupt):
        curvature(problem, u, 4, 0, stop=lambda: True)


def test_a_fit_with_a_mask_free_reports_its_texels_sd(tmp_path):
    """Adam moves the mask and `gn` the ior with the texels held: the result holds the mask's
    sd, the texture's shape, small where the view looks, the uniform sd where it never does;
    the texels the view sees well near the painted mask."""
    problem, u = mask_problem(tmp_path, 24, 24)
    values = problem.values(u) | {"glaze.ior": 1.3}
    adam = Phase(solver="adam", steps=60, spp=8, lr=0.1, average=0.5)
    gn = Phase(solver="gn", steps=4, spp=16, jacobian_spp=16)
    result = run_schedule(problem, values, (adam, gn), seed=1, uncertainty_spp=16)
    assert set(result.texture_std) == {"glaze.mask.texture"}
    sd = result.texture_std["glaze.mask.texture"]
    assert sd.shape == (4, 4, 1) and np.all(np.isfinite(sd)) and np.all(sd > 0)
    assert np.all(sd <= UNIFORM + 1e-7)
    assert np.any(np.isclose(sd, UNIFORM)), sd[..., 0]  # the far side
    well = sd < 0.1
    assert well.sum() >= 2, sd[..., 0]
    assert 0 < result.texture_seen["glaze.mask.texture"] < 1
    texels = np.asarray(result.values["glaze.mask.texture"]).reshape(4, 4, 1)
    # measured: the four well-seen texels 0.07-0.13 off (1.3-5.6 sd: a texel's sd holds its
    # neighbours, which share its pixels through the bilinear lookup)
    assert np.all(np.abs(texels - MASK)[well] < 0.2), (texels[..., 0], sd[..., 0])
    assert abs(result.values["glaze.ior"] - 1.5) < 3 * result.std["glaze.ior"]


def test_a_fit_of_a_mask_alone_reports_its_texels_sd(tmp_path):
    """With the mask's texture the only free value (Adam alone, no uncertainty of scalars), its
    texels still get their sd, rendered at the last phase's resolution."""
    problem, u = mask_problem(tmp_path, 16, 16)
    problem = Problem(problem.capture, problem.material, problem.free[:1])
    assert [f.key for f in problem.free] == ["glaze.mask.texture"]
    adam = Phase(solver="adam", steps=10, spp=4, lr=0.1)
    result = run_schedule(problem, problem.values(u[:16]), (adam,), seed=1, uncertainty_spp=8)
    assert result.std is None
    sd = result.texture_std["glaze.mask.texture"]
    assert sd.shape == (4, 4, 1) and np.all(sd > 0) and np.all(sd <= UNIFORM + 1e-7)
    assert np.any(sd < 0.5 * UNIFORM) and np.any(np.isclose(sd, UNIFORM)), sd[..., 0]


def test_a_run_folder_holds_the_masks_sd_and_the_scalars_labels(tmp_path):
    """`layerfit fit` with a mask's texture free beside scalars: `<key>.sd.exr` beside the
    texture, the summary's texture entry with its median over the seen texels, the report's sd
    image; the correlation's labels name its scalars alone (it has no texels), one per row."""
    import json
    import tomllib

    from test_stained import TRUTH, material, stain_texture

    from captures.images import read_image
    from fit import recovery
    from fit.commands.fit import fit
    from fit.commands.synth import synthesize

    write_image(tmp_path / "stain.exr", stain_texture())
    table = tomllib.loads(material(TRUTH, TRUTH["stain.reflectance"], 'texture = "stain.exr"\n'))
    truth = build_material(table["material"], tmp_path / "truth.toml")
    synthesize(recovery.studio("sphere", 32, 24), truth, tmp_path / "capture", spp=64)
    (tmp_path / "fit.toml").write_text(
        'capture = "capture"\n[fit]\nfree = ["glaze.ior", "stain.reflectance", '
        '"stain.mask.texture"]\n[fit.textures]\n"stain.mask.texture" = [8, 4]\n'
        '[[fit.phases]]\nsolver = "adam"\nsteps = 10\nspp = 4\nlr = 0.1\n'
        '[[fit.phases]]\nsolver = "gn"\nsteps = 2\nspp = 8\njacobian_spp = 8\n'
        + material(TRUTH, [0.5] * 3)
    )
    summary, out = fit(tmp_path / "fit.toml", tmp_path / "run")
    labels = summary["correlation_labels"]
    assert labels == ["glaze.ior", *(f"stain.reflectance[{i}]" for i in range(3))]
    assert len(summary["correlation"]) == len(labels)
    entry = summary["textures"]["stain.mask.texture"]
    sd = read_image(out / entry["sd_file"])
    assert sd.shape == (4, 8, 1) and np.all(sd <= UNIFORM + 1e-6)
    assert entry["smoothness"] is None and 0 < entry["seen"] <= 1
    below = sd[sd < UNIFORM * (1 - 1e-4)]
    if below.size:
        assert entry["median_sd"] == np.median(below)
    else:
        assert entry["median_sd"] is None
    assert json.loads((out / "summary.json").read_text())["textures"] == summary["textures"]
    assert "stain.mask.texture sd" in (out / "report.html").read_text()
