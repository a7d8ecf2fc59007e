"""Recovering a 16x16 painted mask texel by texel in reverse mode (a two-layer sphere)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from captures.capture import Capture, View
from captures.errors import InputError
from captures.images import write_image
from captures.scene import Camera
from fit.config import load_render_config
from fit.material import build_material, resolve
from fit.render import Renderer, load_scene, render, scene_dict
from fit.solvers import Phase, Problem, run_schedule

ROOT = Path(__file__).resolve().parents[2]
SIZE = 16
ANGLES = [0, 120, 240]  # cameras around the sphere (degrees)


def truth_texture() -> np.ndarray:
    """Blocks of 4x4 texels, alternately mostly glaze and mostly clay."""
    rows, cols = np.indices((SIZE, SIZE)) // 4
    return np.where((rows + cols) % 2 == 0, 0.9, 0.1).astype(np.float32)[..., None]


def material(texture: Path):
    """Clay under a blue glaze whose mask is the texture (threshold 0: the fbm factor is ~1)."""
    table = {
        "type": "layered",
        "layers": [
            {"name": "clay", "type": "oren_nayar", "reflectance": [0.8, 0.75, 0.7]},
            {
                "name": "glaze",
                "type": "glaze",
                "pigment": [0.1, 0.22, 0.55],
                "mask": {"texture": str(texture), "threshold": 0.0, "softness": 0.005},
            },
        ],
    }
    return build_material(table, texture.parent / "material.toml")


def capture(tmp_path: Path) -> Capture:
    """Three views of the sphere with the true mask (and a brighter sky to see it by)."""
    write_image(tmp_path / "truth.exr", truth_texture())
    truth = material(tmp_path / "truth.exr")
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    cameras = tuple(
        Camera((5 * np.sin(a), -5 * np.cos(a), 0.5), (0, 0, 0), (0, 0, 1), 30.0, 48, 36)
        for a in np.radians(ANGLES)
    )
    scene = dataclasses.replace(cfg.scene, cameras=cameras, environment=(0.5, 0.5, 0.5))
    views = []
    for i, camera in enumerate(cameras):
        image = render(load_scene(scene_dict(scene, truth, i, 256)), 256, seed=7 + i)
        views.append(View(f"v{i}", image, np.ones((36, 48), np.float32), camera))
    return Capture(scene, views)


def test_mask_texture_is_recovered_in_reverse_mode(tmp_path):
    """From a uniform 0.5 start, 50 Adam steps (8 spp, fresh seeds) recover the 4x4-block
    pattern in the band the cameras see face-on (rows 4-11, within 45 degrees of the equator;
    measured mean error 0.04); the poles, seen at grazing angles or not at all, stay uncertain."""
    target = capture(tmp_path)
    write_image(tmp_path / "start.exr", np.full((SIZE, SIZE, 1), 0.5, np.float32))
    start_material = material(tmp_path / "start.exr")
    free = resolve(start_material, ["glaze.mask.texture"])
    assert free[0].shape == (SIZE, SIZE, 1) and free[0].size == SIZE * SIZE
    problem = Problem(target, start_material, free)
    start = {"glaze.mask.texture": np.full(SIZE * SIZE, 0.5).tolist()}
    result = run_schedule(problem, start, (Phase(solver="adam", steps=50, spp=8, lr=0.2),), seed=0)
    fitted = np.asarray(result.values["glaze.mask.texture"]).reshape(SIZE, SIZE)
    truth = truth_texture()[..., 0]
    band = slice(4, 12)
    assert np.abs(fitted[band] - truth[band]).mean() < 0.08
    assert np.corrcoef(fitted[band].ravel(), truth[band].ravel())[0, 1] > 0.9
    assert result.std is None  # 256 components: no Jacobian-based uncertainty
    # the texture's passes (not frozen) left no AD graph behind in its scenes: a frozen pass of
    # another fit in this process (a Ray worker's next task) failed on it in `ad_traverse()`
    other = Renderer(target, start_material, resolve(start_material, ["glaze.roughness"]))
    _, jac = other.jacobian(np.array([0.1], np.float32), 0, 1)
    assert np.isfinite(jac).all() and np.any(jac != 0)
    with pytest.raises(InputError, match=r"every free parameter is a texture: no scalar.*adam"):
        run_schedule(problem, start, (Phase(solver="gn", steps=2, spp=1),), seed=0)


def test_a_small_texture_fits_to_its_end_without_forward_mode(tmp_path):
    """An 8x8 mask (64 components, within the uncertainty's count) ended every fit with an
    internal error: the uncertainty's forward-mode Jacobian through a bitmap's texels fails in
    Mitsuba 3.9 (`dr.isolate_grad` scope), after all the steps, and the run folder was never
    written. The fit now ends without an sd for it; `gn` and `lm`, with no scalar to move
    while the texture is held, refuse by name; the default schedule of a texture alone is its
    Adam phases, and phases of `gn` a config gives are refused before any render."""
    from fit.commands.fit import prepare
    from fit.commands.synth import synthesize
    from fit.config import load_fit_config
    from fit.material import save_preset

    target = capture(tmp_path)
    write_image(tmp_path / "start8.exr", np.full((8, 8, 1), 0.5, np.float32))
    start_material = material(tmp_path / "start8.exr")
    problem = Problem(target, start_material, resolve(start_material, ["glaze.mask.texture"]))
    start = {"glaze.mask.texture": np.full(64, 0.5).tolist()}
    result = run_schedule(problem, start, (Phase(solver="adam", steps=2, spp=1),), seed=0)
    assert np.isfinite(result.values["glaze.mask.texture"]).all() and result.std is None
    for solver in ("gn", "lm"):
        with pytest.raises(InputError, match=r"every free parameter is a texture: no scalar"):
            run_schedule(problem, start, (Phase(solver=solver, steps=1, spp=1),), seed=0)

    synthesize(target.scene, start_material, tmp_path / "cap", spp=1)
    (tmp_path / "fit.toml").write_text(
        'capture = "cap"\nmaterial = "material.toml"\n[fit]\nfree = ["glaze.mask.texture"]\n'
    )
    save_preset(start_material, tmp_path / "material.toml")
    cfg = load_fit_config(tmp_path / "fit.toml")
    assert [p.solver for p in cfg.phases] == ["adam", "adam"]  # the texture schedule's Adam
    prepare(cfg, trace=False)
    (tmp_path / "fit.toml").write_text(
        (tmp_path / "fit.toml").read_text() + '[[fit.phases]]\nsolver = "gn"\nsteps = 2\nspp = 4\n'
    )
    with pytest.raises(InputError) as err:
        prepare(load_fit_config(tmp_path / "fit.toml"), trace=False)
    message = str(err.value)
    assert "fit.phases[0].solver = 'gn': every free parameter is a texture" in message


def test_two_masks_sharing_a_file_keep_their_own_fitted_texels(tmp_path):
    """Glaze and lime masks read one painted file; the glaze's is fitted. The preset named the
    lime's unfitted copy for both (its files were kept by source path), and the report's mask
    panel was baked from the starting texture: the fitted texels reach the preset, the lime
    keeps the file's, and the report bakes the fitted one."""
    from captures.images import read_image
    from fit.commands.fit import run_fit
    from fit.commands.synth import synthesize
    from fit.config import load_fit_config
    from fit.material import load_preset, save_preset

    target = capture(tmp_path)
    painted = np.linspace(0.2, 0.8, 64, dtype=np.float32).reshape(8, 8, 1)
    write_image(tmp_path / "paint.exr", painted)
    table = material(tmp_path / "paint.exr").table()
    lime = {"name": "lime", "type": "oren_nayar", "reflectance": [0.86, 0.85, 0.8]}
    lime["mask"] = {"texture": str(tmp_path / "paint.exr"), "threshold": 0.0, "seed": 3}
    table["layers"].append(lime)
    shared = build_material(table, tmp_path / "material.toml")
    synthesize(target.scene, shared, tmp_path / "cap", spp=1)
    save_preset(shared, tmp_path / "start.toml")
    (tmp_path / "fit.toml").write_text(
        'capture = "cap"\nmaterial = "start.toml"\n[fit]\nfree = ["glaze.mask.texture"]\n'
        'uncertainty_spp = 1\n[[fit.phases]]\nsolver = "adam"\nsteps = 3\nspp = 1\nlr = 0.3\n'
    )
    cfg = load_fit_config(tmp_path / "fit.toml")
    summary = run_fit(cfg, tmp_path / "run")
    fitted = np.asarray(summary["values"]["glaze.mask.texture"], np.float32).reshape(8, 8, 1)
    assert np.abs(fitted - painted).max() > 0.05  # the steps moved it
    preset = load_preset(tmp_path / "run" / "preset.toml").material
    files = preset.texture_files()
    assert files["glaze.mask.texture"] != files["lime.mask.texture"]
    np.testing.assert_allclose(read_image(files["glaze.mask.texture"]), fitted, atol=1e-6)
    np.testing.assert_allclose(read_image(files["lime.mask.texture"]), painted, atol=1e-6)
    # the report's mask is the fitted texture (x fbm): baked again from the preset, it matches
    from fit.commands.run_folder import masks as _masks

    report = read_image(tmp_path / "run" / "report" / "mask-00-glaze.mask.png")
    baked_fitted, baked_start = _masks(preset)["glaze.mask"], _masks(shared)["glaze.mask"]
    grey = report if report.ndim == 2 else report[..., 0]
    assert grey.shape == baked_fitted.shape
    fitted_off = np.abs(grey - baked_fitted).mean()
    assert fitted_off < 0.5 * np.abs(grey - baked_start).mean(), fitted_off
