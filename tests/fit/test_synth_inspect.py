"""`synth` writes captures that load back to what was rendered; `inspect` matches silhouettes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli

from captures import open_capture
from captures.capture import load_capture
from captures.images import read_image
from fit.commands.inspect import contact_sheet, iou, silhouettes
from fit.commands.synth import Degradation, synthesize
from fit.config import load_render_config

ROOT = Path(__file__).resolve().parents[2]


def small_sphere():
    import dataclasses

    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    cams = tuple(dataclasses.replace(c, width=40, height=30) for c in cfg.scene.cameras)
    return cfg, dataclasses.replace(cfg.scene, cameras=cams)


def test_synth_round_trip(tmp_path):
    cfg, scene = small_sphere()

    def make(folder):
        return synthesize(
            scene, cfg.material, folder, spp=16, seed=3, degradation=Degradation(exposure_ev=0.5)
        )

    out = make(tmp_path / "cap")
    capture = load_capture(out)
    assert capture.truth == {
        "glaze.pigment": [0.1, 0.22, 0.55],
        "glaze.roughness": 0.0625,
        "glaze.ior": 1.52,
        "glaze.sigma": 0.0,  # every declared parameter of the truth, defaults included
    }
    (view,) = capture.views
    assert view.gain != 1.0  # a random exposure was applied, recorded, and undone on load

    from fit.render import load_scene, render, scene_dict

    again = render(load_scene(scene_dict(scene, cfg.material, 0, 16)), 16, seed=3)
    np.testing.assert_allclose(view.image, again, rtol=1e-4, atol=1e-6)
    # deterministic: same config and seed, same pixels up to float rounding (the film sums each
    # pixel's samples with parallel atomics, whose order varies)
    out2 = make(tmp_path / "cap2")
    np.testing.assert_allclose(
        read_image(out / "view_00.exr"), read_image(out2 / "view_00.exr"), rtol=1e-5, atol=1e-7
    )


def test_synth_noise_and_formats(tmp_path):
    cfg, scene = small_sphere()
    clean = synthesize(scene, cfg.material, tmp_path / "a", spp=8, seed=1)
    noisy = synthesize(
        scene,
        cfg.material,
        tmp_path / "b",
        spp=8,
        seed=1,
        degradation=Degradation(shot=0.01, read=0.01),
    )
    jpg = synthesize(scene, cfg.material, tmp_path / "c", spp=8, seed=1, fmt="jpg")
    a, b = load_capture(clean).views[0].image, load_capture(noisy).views[0].image
    residual = (b - a)[a.sum(-1) > 0]
    assert 0.005 < residual.std() < 0.1
    c = load_capture(jpg)
    assert 'encoding = "srgb"' in (jpg / "capture.toml").read_text()
    inside = c.views[0].weight > 0
    assert np.abs(c.views[0].image - a)[inside].mean() < 0.02  # 8-bit JPEG of the same render


def test_synth_never_overwrites_and_leaves_nothing_on_failure(tmp_path):
    cfg, scene = small_sphere()
    (tmp_path / "taken").mkdir()
    with pytest.raises(FileExistsError):
        synthesize(scene, cfg.material, tmp_path / "taken", spp=4)
    with pytest.raises(ValueError, match="format"):
        synthesize(scene, cfg.material, tmp_path / "new", spp=4, fmt="gif")
    bad = dataclasses.replace(cfg.material, bsdf={**cfg.material.bsdf, "roughness": "no"})
    with pytest.raises(RuntimeError):  # Mitsuba refuses the material mid-way
        synthesize(scene, bad, tmp_path / "half", spp=4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_peer_silhouette_matches(shared_data):
    capture = open_capture(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    for view, coverage in zip(capture.views, silhouettes(capture, spp=64), strict=True):
        assert iou(coverage, view.mask, view.mask_coverage) > 0.98


def test_diligent_silhouette_and_shading_match(shared_data):
    """The fitted sphere covers the mask, and a Lambertian render under each view's light
    correlates with the photo (a mirrored light frame would not)."""

    from fit.render import load_scene, render, scene_dict

    capture = open_capture(shared_data / "diligent-ball", downscale=4)
    coverage = silhouettes(capture, spp=16)
    assert iou(coverage[0], capture.views[0].mask, 0.5) > 0.98
    for i in (0, 7, 12):
        image = render(load_scene(scene_dict(capture.scene_of(i), {"type": "diffuse"}, 0, 16)), 16)
        valid = capture.views[i].weight > 0
        r = np.corrcoef(image.mean(-1)[valid], capture.views[i].image.mean(-1)[valid])[0, 1]
        assert r > 0.95, (i, r)


def test_inspect_command(tmp_path, shared_data):
    scene_json = shared_data / "peer-cycles" / "sphere-blue" / "scene.json"
    out = run_cli("inspect", scene_json, "--sheet", tmp_path / "sheet.png")
    assert out.returncode == 0, out.stderr
    assert "view_00" in out.stderr and "0.99" in out.stderr
    assert "mesh mesh.obj" in out.stderr  # the object, in the title
    assert (tmp_path / "sheet.png").stat().st_size > 10_000
    # a DiLiGenT folder's 16 views: the sheet shows 8, and says so (it stopped without a word)
    out = run_cli(
        "inspect", shared_data / "diligent-ball", "--downscale", "8", "--sheet", tmp_path / "d.png"
    )
    assert out.returncode == 0, out.stderr
    assert "d.png (the first 8 views)" in out.stderr.replace("\n", "")


def test_contact_sheet_without_silhouette(tmp_path):
    cfg, scene = small_sphere()
    capture = load_capture(synthesize(scene, cfg.material, tmp_path / "cap", spp=4))
    sheet = contact_sheet(capture, None, tmp_path / "s.png")
    assert sheet.stat().st_size > 5_000


def test_synth_records_the_diffuse_lobe_its_truth_belongs_to(tmp_path, caplog):
    """A capture rendered with the EON lobe says so (`[truth_options]`): a fit with the
    qualitative lobe warns and does not score sigma against EON's roughness; one with EON does."""
    from fit.commands.prepare import check_truth
    from fit.material import build_material

    _, scene = small_sphere()
    scene = dataclasses.replace(scene, cameras=scene.cameras[:1])
    table = {"type": "glaze", "sigma": 0.5, "diffuse": "eon"}
    out = synthesize(scene, build_material(table, "<truth>"), tmp_path / "cap", spp=2)
    assert '[truth_options]\n"glaze.diffuse" = "eon"' in (out / "capture.toml").read_text()
    capture = load_capture(out)
    assert capture.truth_options == {"glaze.diffuse": "eon"}
    check_truth(capture, [], out, build_material(table, "<fit>"))
    assert capture.truth["glaze.sigma"] == 0.5 and not caplog.records
    check_truth(capture, [], out, build_material({**table, "diffuse": "qualitative"}, "<fit>"))
    assert "glaze.sigma" not in capture.truth
    assert "set diffuse = 'eon' on the glaze layer" in caplog.records[0].getMessage()


def test_synth_keeps_a_scene_file_named_like_a_view(tmp_path):
    """An environment map named `view_00.exr` is copied under another name: the first view's
    image overwrote it, and the capture was then lit by its own photo."""
    from captures.images import write_image
    from captures.scene import EnvMap

    cfg, scene = small_sphere()
    sky = np.full((8, 16, 3), 0.2, np.float32)
    (tmp_path / "sky").mkdir()
    write_image(tmp_path / "sky" / "view_00.exr", sky)
    scene = dataclasses.replace(scene, environment=EnvMap(tmp_path / "sky" / "view_00.exr", 1.0))
    out = synthesize(scene, cfg.material, tmp_path / "cap", spp=2)
    capture = load_capture(out)
    assert capture.scene.environment.path.name == "scene-view_00.exr"
    np.testing.assert_array_equal(read_image(capture.scene.environment.path), sky)
    assert read_image(out / "view_00.exr").shape == (30, 40, 3)


def test_inspect_warns_of_a_mask_the_silhouette_does_not_match(tmp_path):
    """An inverted object mask: `inspect` says so in a warning, as `fit` does (it showed only an
    IoU of 0.04 in its table)."""
    import tomllib

    import tomli_w

    from captures.images import write_image
    from fit.commands.synth import synthesize
    from fit.config import load_render_config

    root = Path(__file__).resolve().parents[2]
    cfg = load_render_config(root / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=32, height=24)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    synthesize(scene, cfg.material, tmp_path / "cap", spp=4, seed=1)
    manifest = tmp_path / "cap" / "capture.toml"
    doc = tomllib.loads(manifest.read_text())
    coverage = silhouettes(load_capture(manifest))[0]
    for inverted, name in ((False, "right.png"), (True, "inverted.png")):
        mask = (coverage > 0.5) != inverted
        write_image(tmp_path / "cap" / name, np.repeat(mask[..., None], 3, 2).astype(np.float32))
        doc["views"][0]["mask"] = name
        manifest.write_text(tomli_w.dumps(doc))
        out = run_cli("inspect", tmp_path / "cap", "--sheet", tmp_path / f"{name}.sheet.png")
        assert out.returncode == 0, out.stderr
        warned = "overlaps the object mask of 1 of 1 views poorly" in out.stderr.replace("\n", "")
        assert warned == inverted, out.stderr


def test_inspect_run_again_redraws_its_default_sheet_only(tmp_path, monkeypatch):
    """`inspect` run twice replaces its own default sheet (out/inspect-<name>.png, tagged by
    layerfit; it was refused without --force); a sheet named with --sheet, or a file there that
    layerfit did not draw, is still refused."""
    from typer.testing import CliRunner

    from fit.cli import app

    cfg, scene = small_sphere()
    synthesize(scene, cfg.material, tmp_path / "cap", spp=4)
    monkeypatch.chdir(tmp_path)
    runner, sheet = CliRunner(), tmp_path / "out" / "inspect-cap.png"
    for _ in range(2):
        result = runner.invoke(app, ["inspect", "cap", "--no-silhouette"])
        assert result.exit_code == 0, result.output
        assert sheet.stat().st_size > 5_000
    result = runner.invoke(app, ["inspect", "cap", "--no-silhouette", "--sheet", str(sheet)])
    assert result.exit_code == 2 and "--force" in result.output
    sheet.write_bytes(b"a user's file")
    result = runner.invoke(app, ["inspect", "cap", "--no-silhouette"])
    assert result.exit_code == 2 and sheet.read_bytes() == b"a user's file"


@pytest.mark.parametrize("limit, noted", [(10**9, False), (100, True)])
def test_inspect_notes_large_views_with_a_downscale(tmp_path, monkeypatch, limit, noted):
    """Three 6000x4000 photos took `inspect` 2 minutes and 7 GB without a word: above
    `LARGE_VIEW` pixels a view it says so first, with the `--downscale` that shows them at about
    a million pixels."""
    import math

    from typer.testing import CliRunner

    import fit.commands.inspect
    from fit.cli import app

    cfg, scene = small_sphere()
    synthesize(scene, cfg.material, tmp_path / "cap", spp=4)
    monkeypatch.setattr(fit.commands.inspect, "LARGE_VIEW", limit)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["inspect", "cap"])
    assert result.exit_code == 0, result.output
    camera = scene.cameras[0]
    factor = math.ceil(math.sqrt(camera.width * camera.height / 1e6))
    said = f"note: views of up to {camera.width}x{camera.height}" in result.output
    assert said == noted, result.output
    if noted:
        assert f"--downscale {factor} shows them" in " ".join(result.output.split())
