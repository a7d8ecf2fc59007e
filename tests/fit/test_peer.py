"""The glaze against another team's implementation: Blender Cycles' renders of a blue glazed sphere
(../shared/data/peer-cycles/sphere-blue), at the known parameters, from its scene.json."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from captures import load_peer_scene
from captures.images import read_image
from fit.render import coverage_dict, load_scene, render, scene_dict

ROOT = Path(__file__).resolve().parents[2]
SPP = 1024
# Mean relative pixel error over fully covered pixels. The issue asks < 0.09; measured here at
# 1024 spp: 0.029-0.034 at the truth (mostly Mitsuba's own noise: 0.015 at 4096 spp), 0.044 with
# alpha x 1.5, 0.059 with alpha x 2, 0.10 with alpha x 4. 0.045 still passes the truth with margin
# and rejects a lobe twice too wide.
PIXEL_TOL = 0.045


@pytest.fixture(scope="module")
def peer(shared_data):
    scene = load_peer_scene(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    targets = [read_image(p)[..., :3] for p in scene.meta["images"]]
    coverage = [
        render(load_scene(coverage_dict(scene, v, 64)), 64)[..., 0]
        for v in range(len(scene.cameras))
    ]
    return scene, targets, coverage


def glaze_at_truth(material: dict, fresnel: str) -> dict:
    return {
        "type": "glaze",
        "pigment": {"type": "rgb", "value": material["base_color"]},
        "sigma": material["diffuse_roughness"],
        "roughness": material["specular_roughness"] ** 2,  # Cycles' roughness r: alpha = r^2
        "ior": material["ior"],
        "coupling": "paper",
        "fresnel": fresnel,
    }


@pytest.mark.parametrize(
    "fresnel, radiance_tol",
    [pytest.param("schlick", 0.05, marks=pytest.mark.slow), ("exact", 0.02)],  # Cycles' own
)
def test_glaze_matches_cycles(peer, fresnel, radiance_tol):
    """Per view: total object radiance within 5 % (Schlick) / 2 % (exact Fresnel, what Cycles
    uses), and mean relative pixel error over fully covered pixels below `PIXEL_TOL` (total radiance
    alone would miss a lobe of the wrong width)."""
    scene, targets, coverage = peer
    bsdf = glaze_at_truth(scene.meta["material"], fresnel)
    for view, (target, cover) in enumerate(zip(targets, coverage, strict=True)):
        image = render(load_scene(scene_dict(scene, bsdf, view, SPP)), SPP, seed=view)
        obj, inside = cover > 0, cover > 0.999
        assert inside.sum() > 1000
        ratio = image[obj].sum() / target[obj].sum()
        assert ratio == pytest.approx(1.0, abs=radiance_tol), f"view {view}: radiance ratio {ratio}"
        rel = np.abs(image[inside] - target[inside]).sum(-1) / target[inside].sum(-1)
        assert rel.mean() < PIXEL_TOL, f"view {view}: mean relative pixel error {rel.mean():.3f}"


def test_wrong_lobe_width_is_caught(peer):
    """The pixel metric can fail: the same material with alpha doubled keeps its total radiance
    close but moves pixels."""
    scene, targets, coverage = peer
    bsdf = glaze_at_truth(scene.meta["material"], "exact")
    bsdf["roughness"] *= 2.0
    image = render(load_scene(scene_dict(scene, bsdf, 0, SPP)), SPP)
    inside = coverage[0] > 0.999
    rel = np.abs(image[inside] - targets[0][inside]).sum(-1) / targets[0][inside].sum(-1)
    ratio = image[coverage[0] > 0].sum() / targets[0][coverage[0] > 0].sum()
    assert abs(ratio - 1) < 0.02 and rel.mean() > PIXEL_TOL, (ratio, rel.mean())


def fit_peer(config: str):
    """(result, truth) of a bundled peer-sphere fit config with its schedule."""
    from captures import open_capture
    from fit.config import load_fit_config
    from fit.material import resolve, start_values
    from fit.solvers import Problem, run_schedule

    cfg = load_fit_config(ROOT / "configs" / config)
    capture = open_capture(cfg.capture)
    free = resolve(cfg.material, cfg.free)
    start = start_values(free)
    return run_schedule(Problem(capture, cfg.material, free), start, cfg.phases), capture.truth


@pytest.mark.slow
def test_peer_sphere_is_recovered(shared_data):
    """configs/peer-sphere.toml with the default schedule (exact Fresnel, as Cycles): its
    targets are alpha within 2 %, ior within 0.02, pigment within 0.01 per channel (measured
    with the split `gn` default: +0.3 %, -0.0008, 0.0002 in 81 s of fit on 2 cores; with the
    EON lobe's sigma free too, 2026-12-01: -0.6 %, -0.0011, 0.0003, sigma 0.0003 for Cycles'
    0; a loaded default run once pushed past 10 minutes by this test: slow target)."""
    result, truth = fit_peer("peer-sphere.toml")
    values = result.values
    np.testing.assert_allclose(values["glaze.pigment"], truth["glaze.pigment"], atol=0.01)
    assert values["glaze.roughness"] == pytest.approx(truth["glaze.roughness"], rel=0.02)
    assert values["glaze.ior"] == pytest.approx(truth["glaze.ior"], abs=0.02)
    assert "glaze.roughness" not in result.poorly_determined


@pytest.mark.slow
def test_peer_sphere_with_schlick(shared_data):
    """configs/peer-sphere-schlick.toml: the model mismatch with Cycles' exact Fresnel shows in
    ior (measured +0.020, alpha -2.5 %, pigment within 0.002)."""
    result, truth = fit_peer("peer-sphere-schlick.toml")
    values = result.values
    np.testing.assert_allclose(values["glaze.pigment"], truth["glaze.pigment"], atol=0.005)
    assert values["glaze.roughness"] == pytest.approx(truth["glaze.roughness"], rel=0.05)
    assert 0.0 < values["glaze.ior"] - truth["glaze.ior"] < 0.035


@pytest.mark.slow
def test_peer_torus_is_recovered_with_a_light_in_view(shared_data):
    """configs/peer-torus.toml, all five views (view_04 sees the torus past the back of light 0,
    which Cycles does not draw): alpha within 5 %, ior within 0.03, pigment within 0.02 (passes;
    88 s on 2 cores, hence the slow target; with the EON lobe's sigma free too, 2026-12-01:
    alpha +3.5 %, ior +0.0028, pigment 0.0002, sigma 0.0003 for Cycles' 0)."""
    result, truth = fit_peer("peer-torus.toml")
    values = result.values
    np.testing.assert_allclose(values["glaze.pigment"], truth["glaze.pigment"], atol=0.02)
    assert values["glaze.roughness"] == pytest.approx(truth["glaze.roughness"], rel=0.05)
    assert values["glaze.ior"] == pytest.approx(truth["glaze.ior"], abs=0.03)


def test_light_seen_from_behind_is_transparent(shared_data):
    """torus-amber view_04 at the true material: no black card where light 0's back stands
    between the camera and the torus (was 4178 black pixels, radiance off 2x)."""
    from captures import open_capture
    from fit.render import Renderer

    capture = open_capture(shared_data / "peer-cycles" / "torus-amber" / "scene.json")
    cfg_material = {
        "type": "glaze",
        "fresnel": "exact",
        "pigment": list(capture.truth["glaze.pigment"]),
        "roughness": capture.truth["glaze.roughness"],
        "ior": capture.truth["glaze.ior"],
    }
    from fit.material import build_material, resolve

    material = build_material(cfg_material)
    free = resolve(material, ["glaze.ior"])
    renderer = Renderer(capture, material, free)
    flat = renderer.render(np.array([capture.truth["glaze.ior"]], np.float32), 0, 32)
    offset = 0
    for view in capture.views:
        n = view.image.size
        image = flat[offset : offset + n].reshape(view.image.shape)
        offset += n
        valid = view.weight > 0
        black = int(np.sum(np.all(image[valid] == 0, axis=-1)))
        ratio = image[valid].mean() / view.image[valid].mean()
        assert black == 0 and abs(ratio - 1) < 0.03, (view.name, black, ratio)


def test_an_eon_truth_is_scored_only_against_an_eon_glaze(caplog):
    """A peer's diffuse roughness is EON's (`truth_options`): an EON glaze scores its sigma; a
    qualitative one does not, and the warning names the option to set."""
    from captures.capture import Capture
    from fit.commands.prepare import check_truth
    from fit.material import build_material

    def capture():
        truth = {"glaze.sigma": 0.5, "glaze.ior": 1.5}
        return Capture(None, [], truth, truth_options={"glaze.diffuse": "eon"})

    table = {"type": "glaze", "sigma": 0.3}
    eon = build_material({**table, "diffuse": "eon"}, "<test>")
    kept = capture()
    check_truth(kept, [], "scene.json", eon)
    assert kept.truth == {"glaze.sigma": 0.5, "glaze.ior": 1.5} and not caplog.records
    dropped = capture()
    check_truth(dropped, [], "scene.json", build_material(table, "<test>"))
    assert dropped.truth == {"glaze.ior": 1.5}
    (record,) = caplog.records
    assert "set diffuse = 'eon' on the glaze layer" in record.getMessage()


def test_a_rough_diffuse_target_needs_the_eon_lobe():
    """A glazed sphere rendered with EON at diffuse roughness 0.7 (as Blender or an OpenPBR
    renderer would), fitted for pigment and sigma from grey: with `diffuse = "eon"` the pigment
    comes back within 0.02; the qualitative Oren-Nayar, which loses energy as it roughens,
    makes up for it with a brighter pigment (measured on the torus at 0.6: +0.096 in red)."""
    from captures.capture import Capture, View
    from fit.material import build_material, resolve, start_values
    from fit.recovery import studio
    from fit.solvers import Phase, Problem, run_schedule

    truth = {"pigment": [0.6, 0.4, 0.2], "sigma": 0.7}
    glaze = {"type": "glaze", "roughness": 0.1, "ior": 1.5, "fresnel": "exact", "diffuse": "eon"}
    scene = studio("sphere", 64, 48)
    target = build_material({**glaze, **truth}, "<truth>")
    views = []
    for i, camera in enumerate(scene.cameras[:2]):
        image = render(load_scene(scene_dict(scene, target, i, 256)), 256, seed=7 + i)
        views.append(View(f"v{i}", image, np.ones(image.shape[:2], np.float32), camera))
    capture = Capture(scene, views, {"glaze.pigment": truth["pigment"]})
    phases = [Phase(solver="adam", steps=60, spp=8, lr=0.08), Phase(solver="gn", steps=16, spp=16)]
    pigment = {}
    for diffuse in ("eon", "qualitative"):
        start = build_material({**glaze, "diffuse": diffuse, "sigma": 0.3}, "<start>")
        free = resolve(start, ["glaze.pigment", "glaze.sigma"])
        problem = Problem(capture, start, free)
        result = run_schedule(problem, start_values(free), phases, uncertainty_spp=8)
        pigment[diffuse] = np.asarray(result.values["glaze.pigment"]) - truth["pigment"]
    assert np.abs(pigment["eon"]).max() < 0.02, pigment
    assert pigment["qualitative"].max() > 0.04, pigment
