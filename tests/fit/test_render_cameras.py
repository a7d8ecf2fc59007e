"""Every camera kind renders frozen (as fast as perspective) and equal to unfrozen; area-averaged
captures of any size line up with renders at the smaller size."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from captures.capture import Capture, View
from fit.config import load_render_config
from fit.material import build_material, resolve
from fit.render import GRAD_SEED_OFFSET, Renderer, load_scene
from fit.render.renderer import RERECORD_LIMIT

ROOT = Path(__file__).resolve().parents[2]


def sphere_capture(kind: str, width: int = 40, height: int = 30) -> tuple[Capture, object]:
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=width, height=height)
    if kind == "thinlens":
        camera = dataclasses.replace(camera, aperture_radius=0.02)
    elif kind == "orthographic":
        camera = dataclasses.replace(camera, kind="orthographic", ortho_width=2.6)
    elif kind == "calibrated":  # a pinhole with its principal point off the image's centre
        point = (0.6 * width + 0.25, 0.42 * height - 0.5)
        camera = dataclasses.replace(camera, principal_point=point)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    view = View("v0", np.zeros((height, width, 3), np.float32), np.ones((height, width)), camera)
    return Capture(scene, [view]), cfg.material


@pytest.mark.parametrize("kind", ["perspective", "thinlens", "orthographic"])
def test_frozen_renders_equal_unfrozen_for_every_camera(kind):
    """Orthographic and thin-lens sensors crashed dr.freeze's recording (Mitsuba 3.9 does not
    declare their derived members to it); the renderer rebuilds them inside the frozen call."""
    capture, material = sphere_capture(kind)
    free = resolve(material, ["glaze.pigment", "glaze.roughness"])
    frozen, plain = Renderer(capture, material, free), Renderer(capture, material, free, False)
    cotangent = np.random.default_rng(0).normal(size=frozen.size).astype(np.float32)
    for values in ([0.2, 0.3, 0.4, 0.1], [0.3, 0.3, 0.2, 0.2], [0.5, 0.1, 0.1, 0.05]):
        x = np.asarray(values, np.float32)
        a, b = frozen.render(x, 3, 4), plain.render(x, 3, 4)
        assert a.max() > 0
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
        # the reverse pass's scatter-adds sum in a thread-dependent order: each component is
        # compared to a thousandth of the largest (roughness's once differed by 0.19 % of itself,
        # 0.004 % of the pigment's)
        grad_frozen, grad_plain = frozen.vjp(x, 3, 4, cotangent), plain.vjp(x, 3, 4, cotangent)
        np.testing.assert_allclose(
            grad_frozen, grad_plain, rtol=1e-3, atol=1e-3 * np.abs(grad_plain).max()
        )


def batch_capture(kinds: list[str]) -> tuple[Capture, object]:
    """Views of the sphere through cameras of `kinds`, each from a little further back."""
    views = []
    for k, kind in enumerate(kinds):
        capture, material = sphere_capture(kind, 24, 18)
        view = capture.views[0]
        origin = tuple(float(c) * (1 + 0.1 * k) for c in view.camera.origin)
        views.append(
            dataclasses.replace(
                view, name=f"v{k}", camera=dataclasses.replace(view.camera, origin=origin)
            )
        )
    return dataclasses.replace(capture, views=views), material


@pytest.mark.parametrize(
    "kinds",
    [  # the mixed batch holds both kinds: the others add 23 s on an AVX2 CPU (slow target)
        pytest.param(["thinlens"] * 3, marks=pytest.mark.slow),
        pytest.param(["orthographic"] * 2, marks=pytest.mark.slow),
        ["thinlens", "orthographic", "perspective"],
    ],
)
def test_a_batch_of_any_cameras_renders_frozen_and_right_beside_other_scenes(kinds, capfd):
    """Views of thin-lens or orthographic cameras rendered through one `batch` sensor, frozen,
    replayed wrong derivatives once other scenes were alive in the process (live perspective
    scenes: the Jacobian off by up to 220; in the full test suite, 3 runs of 3). They render one
    sensor each: with other scenes alive (perspective, thin-lens, orthographic), the frozen
    primal, reverse and forward passes stay frozen and equal an unfrozen renderer's over
    several replays."""
    capture, material = batch_capture(kinds)
    free = resolve(material, ["glaze.pigment", "glaze.roughness", "glaze.ior"])
    others = []
    for kind in ("perspective", "thinlens", "orthographic", "perspective"):
        other_capture, other_material = sphere_capture(kind, 8, 6)
        other_free = resolve(other_material, ["glaze.roughness"])
        other = Renderer(other_capture, other_material, other_free)
        assert other.render(np.asarray([0.2], np.float32), 0, 1).max() > 0
        others.append(other)
    rng = np.random.default_rng(1)
    xs = [
        np.asarray(v, np.float32)
        for v in ([0.2, 0.3, 0.4, 0.1, 1.5], [0.5, 0.1, 0.1, 0.05, 1.3], [0.3, 0.3, 0.3, 0.2, 1.4])
    ]
    plain = Renderer(capture, material, free, False)
    cotangent = rng.normal(size=plain.size).astype(np.float32)
    shared = 3 + GRAD_SEED_OFFSET  # `render_vjp` at this seed: the reverse pass of `vjp`'s
    expected = [
        (
            plain.render(x, 3, 4),
            plain.vjp(x, 3, 4, cotangent),
            plain.jacobian(x, 3, 2)[1],
            plain.render(x, shared, 4),
        )
        for x in xs
    ]
    frozen = Renderer(capture, material, free)
    (group,) = frozen.groups
    for _ in range(2):  # recordings, then replays
        for x, (image, grad, jac, shared_image) in zip(xs, expected, strict=True):
            np.testing.assert_allclose(frozen.render(x, 3, 4), image, rtol=1e-4, atol=1e-6)
            # a small component differed 1.4 % in one order of the suite (a path's branch, as
            # below): held to 1e-3 of the largest; wrong replays were 15-35 % off
            scale = 1e-3 * float(np.abs(grad).max())
            np.testing.assert_allclose(frozen.vjp(x, 3, 4, cotangent), grad, rtol=0.01, atol=scale)
            # one pass: the image of its own primal pass (its radiance stored between two
            # kernels, where `render` has one: a branch's rounding now and then flips a
            # sample, measured 2 of 1296 pixels) and the same gradient
            one_image, one_grad = frozen.render_vjp(x, shared, 4, cotangent)
            flipped = ~np.isclose(one_image, shared_image, rtol=1e-4, atol=1e-6)
            assert flipped.mean() < 0.005, flipped.mean()
            np.testing.assert_allclose(one_grad, grad, rtol=0.01, atol=5 * scale)
            mismatched = ~np.isclose(frozen.jacobian(x, 3, 2)[1], jac, rtol=1e-3, atol=1e-5)
            # beside other scenes a sample's path now and then differs (float rounding at a
            # branch): measured up to 15 of 19440 entries; the wrong replays were 15-35 %
            assert mismatched.mean() < 0.005, mismatched.mean()
    passes = (
        group.primal,
        group.reverse,
        group.jacobian_primal,
        group.jacobian_column,
        group.reverse_imaged,
    )
    if len(set(kinds)) == 1:
        assert all(f.frozen is not None for f in passes)
    else:  # a thin-lens sensor beside other kinds records again on every call: then plain
        assert all(
            f.frozen is not None or max(f.recorded.values()) > RERECORD_LIMIT for f in passes
        )
    assert "has been recorded" not in capfd.readouterr().err


@pytest.mark.parametrize("kinds", [["perspective"] * 2, ["thinlens"] * 2])
def test_each_pass_records_once(kinds):
    """A frozen pass records once per sensor and sample count, then replays as seeds, values and
    cotangents change. A literal seed, the film's storage made by a pass's first call, and a
    NumPy cotangent's alignment each made Dr.Jit record a pass again (the cup's reverse pass: 11
    recordings of its 5 sensors). Thin lenses, one sensor each, are rebuilt inside each pass
    (`_rebuild_sensor`): the first sensor's first pass records once more, having seen the other
    sensors before their first rebuild."""
    capture, material = batch_capture(kinds)
    renderer = Renderer(capture, material, resolve(material, ["glaze.roughness"]))
    (group,) = renderer.groups
    passes = (group.primal, group.reverse, group.jacobian_primal, group.jacobian_column)
    rng = np.random.default_rng(0)
    counts = []
    for k in range(4):
        x = np.asarray([0.1 + 0.05 * k], np.float32)
        cotangent = rng.normal(size=renderer.size).astype(np.float32)
        renderer.render(x, k, 4)
        renderer.vjp(x, k, 4, cotangent)
        renderer.jacobian(x, k, 2)
        counts.append([f.frozen.n_recordings for f in passes])
    sensors = len(group.parts)
    first = 1 if sensors > 1 else 0
    assert counts[-1] == [sensors + first, sensors, sensors, sensors], counts
    assert counts[1] == counts[-1], counts  # replays from the second call on


def test_a_schedule_at_two_resolutions_renders_thin_lens_views_frozen():
    """The default schedule's half-resolution scenes stay alive beside the full-resolution ones:
    a thin-lens batch's full-resolution passes are frozen all the same (the cup: a `gn` phase of
    8 steps 125 s re-traced, 44 s frozen)."""
    from fit.solvers import Problem, run_schedule
    from fit.solvers.schedule import Phase

    capture, material = batch_capture(["thinlens"] * 2)
    problem = Problem(capture, material, resolve(material, ["glaze.roughness"]))
    phases = (
        Phase(solver="adam", steps=1, spp=1, downscale=2, lr=0.05),
        Phase(solver="gn", steps=2, spp=1, jacobian_spp=1),
    )
    result = run_schedule(problem, {"glaze.roughness": 0.2}, phases, 0, uncertainty_spp=2)
    assert np.isfinite(result.values["glaze.roughness"])
    for downscale in (1, 2):
        (group,) = problem.renderer(downscale).groups
        assert len(group.parts) == 2
        assert all(
            f.frozen is not None for f in (group.primal, group.reverse, group.jacobian_column)
        )


def test_a_recording_that_fails_runs_unfrozen():
    """A thin-lens scene loaded outside any renderer and still alive is traced into a perspective
    batch's recording (its virtual call on the cameras traces every live camera) unrebuilt, and
    the recording fails: the renderer then runs that pass unfrozen, with the same image, instead
    of failing the fit."""

    from fit.render.scene import scene_dict

    capture, material = batch_capture(["perspective"] * 2)
    free = resolve(material, ["glaze.roughness"])
    x = np.asarray([0.2], np.float32)
    expected = Renderer(capture, material, free, False).render(x, 3, 4)
    stray_capture, _ = sphere_capture("thinlens")
    stray = load_scene(scene_dict(stray_capture.scene_of(0), material, 0, 2))
    frozen = Renderer(capture, material, free)
    primal = frozen.groups[0].primal
    assert primal.frozen is not None
    np.testing.assert_allclose(frozen.render(x, 3, 4), expected, rtol=1e-4, atol=1e-6)
    assert primal.frozen is None  # the recording failed: unfrozen from then on
    del stray


@pytest.mark.parametrize("kind", ["perspective", "orthographic", "calibrated"])
@pytest.mark.parametrize("size", [(40, 30), (45, 33), (41, 31)])
def test_downscaled_capture_of_any_size_matches_a_smaller_render(kind, size):
    """A render at any size, area-averaged by 2, equals a render of the downscaled camera (the
    default schedule's half-resolution phase on any photo). Measured mean |difference| / mean:
    0.046-0.060 at odd sizes, 0.049-0.055 where 2 divides (Monte Carlo noise at the silhouette),
    0.15-0.18 for a camera off by one pixel of width."""
    capture, _ = sphere_capture(kind, *size)
    material = build_material({"type": "oren_nayar", "reflectance": [0.5] * 3, "sigma": 0.3})
    free = resolve(material, ["oren_nayar.sigma"])
    x = np.asarray([0.3], np.float32)
    full = Renderer(capture, material, free, False).render(x, 1, 256).reshape(size[1], size[0], 3)
    capture.views[0] = dataclasses.replace(capture.views[0], image=full)
    small = capture.downscaled(2)
    (view,) = small.views
    assert view.image.shape[:2] == (view.camera.height, view.camera.width)
    render = Renderer(small, material, free, False).render(x, 2, 512).reshape(view.image.shape)
    inside = view.weight > 0.999
    error = np.abs(render - view.image)[inside].mean() / view.image[inside].mean()
    assert error < 0.08, error


@pytest.mark.parametrize("kind", ["perspective", "thinlens"])
def test_batched_views_come_back_in_the_captures_order(kind):
    """Eleven views (more than nine: names must not sort 10 before 2) rendered from one scene
    (a `batch` sensor, or thin-lens cameras one sensor each) equal the same views rendered one
    scene each, view by view."""
    capture, _ = sphere_capture(kind, 12, 9)
    base = capture.views[0]
    views = []
    for k in range(11):  # the camera backs off: each view's sphere is smaller
        origin = tuple(float(c) * (1 + 0.15 * k) for c in base.camera.origin)
        camera = dataclasses.replace(base.camera, origin=origin)
        views.append(dataclasses.replace(base, name=f"v{k}", camera=camera))
    capture = dataclasses.replace(capture, views=views)
    material = build_material({"type": "oren_nayar", "reflectance": [0.5] * 3, "sigma": 0.3})
    free = resolve(material, ["oren_nayar.sigma"])
    x = np.asarray([0.3], np.float32)
    batched = Renderer(capture, material, free, freeze=False)
    single = Renderer(capture, material, free, freeze=False, batch=False)
    assert len(batched.groups) == 1 and len(single.groups) == 11
    a = batched.render(x, 1, 2048).reshape(11, -1).mean(axis=1)
    b = single.render(x, 2, 2048).reshape(11, -1).mean(axis=1)
    assert np.all(np.diff(b) < 0)  # distinct views, darker as the sphere shrinks
    np.testing.assert_allclose(a, b, rtol=0.03)  # noise ~1 %; neighbours differ by >= 5 %


def test_a_sensor_per_view_records_quietly(capfd):
    """Thin-lens views record once per sensor and spp: five spp values of three views are 15
    recordings, which Dr.Jit's default (a warning on stderr after 10: "this indicates a problem
    with how the frozen function is being called") printed into every cup fit."""
    capture, material = batch_capture(["thinlens"] * 3)
    renderer = Renderer(capture, material, resolve(material, ["glaze.roughness"]))
    x = np.asarray([0.2], np.float32)
    for spp in range(1, 6):
        assert renderer.render(x, 0, spp).max() > 0
    (group,) = renderer.groups
    assert group.primal.frozen is not None and group.primal.frozen.n_recordings >= 15
    assert "indicates a problem" not in capfd.readouterr().err


@pytest.mark.parametrize("kind", ["thinlens", "orthographic"])
def test_views_at_any_distance_share_one_kernel(kind):
    """Each thin-lens view's own clip distances, focus distance and aperture (host literals in
    Mitsuba) compiled a kernel per view: the cup's first run took 5 min 22 s against 3 min 38 s
    for its batch. Views at different distances and fields of view (thin lens) or widths
    (orthographic) render through one kernel."""
    import drjit as dr

    capture, material = batch_capture([kind] * 3)
    views = [
        dataclasses.replace(
            v,
            camera=dataclasses.replace(
                v.camera, fov_x_deg=30.0 + 5 * k, ortho_width=v.camera.ortho_width + 0.2 * k
            ),
        )
        for k, v in enumerate(capture.views)
    ]
    capture = dataclasses.replace(capture, views=views)
    renderer = Renderer(capture, material, resolve(material, ["glaze.roughness"]), False)
    spp, (h, w, _) = 4, renderer.shapes[0]
    dr.kernel_history_clear()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
        assert renderer.render(np.asarray([0.2], np.float32), 0, spp).max() > 0
        history = dr.kernel_history()
    renders = {k["hash"] for k in history if "hash" in k and k["size"] == h * w * spp}
    assert len(renders) == 1, renders


def test_thin_lens_views_stay_frozen_over_many_steps():
    """A thin-lens batch records each sensor's passes again once or twice as Dr.Jit makes
    changing literals opaque; that is not the re-recording on every call that runs a function
    plainly (counted over all sensors it was: the cup's main job ran unfrozen, 5:24 not 3:07)."""
    capture, material = batch_capture(["thinlens"] * 3)
    free = resolve(material, ["glaze.pigment", "glaze.roughness", "glaze.ior"])
    renderer = Renderer(capture, material, free)
    (group,) = renderer.groups
    rng = np.random.default_rng(2)
    cotangent = rng.normal(size=renderer.size).astype(np.float32)
    for step in range(12):
        x = np.asarray([0.3, 0.3, 0.3, 0.1 + 0.01 * step, 1.4], np.float32)
        renderer.render(x, step, 2)
        renderer.vjp(x, step, 2, cotangent)
    for f in (group.primal, group.reverse):
        assert f.frozen is not None and max(f.recorded.values()) <= RERECORD_LIMIT


def _centroid(image: np.ndarray) -> np.ndarray:
    """The (x, y) centre of an image's light, in pixels from the top-left corner."""
    weight = image.sum(axis=-1)
    ys, xs = np.indices(weight.shape) + 0.5
    return np.array([(xs * weight).sum(), (ys * weight).sum()]) / weight.sum()


@pytest.mark.parametrize("batch", [True, False])
def test_a_principal_point_moves_the_image_with_it(batch):
    """A pinhole's principal point moved by (dx, dy) pixels moves the whole image by (dx, dy):
    the object's centroid follows to a small fraction of a pixel, in a `batch` sensor beside a
    centred view as in a sensor of its own. (The sign is Mitsuba's offset's opposite: its
    `principal_point_offset_x` = 0.1 moves the image left by a tenth of the width.)"""
    width, height = 48, 36
    capture, _ = sphere_capture("perspective", width, height)
    base = capture.views[0]
    far = tuple(1.6 * float(c) for c in base.camera.origin)  # the sphere well inside the view
    base = dataclasses.replace(base, camera=dataclasses.replace(base.camera, origin=far))
    shift = np.array([4.0, -3.0])
    point = tuple(np.array([width / 2, height / 2]) + shift)
    moved = dataclasses.replace(base.camera, principal_point=point)
    capture = dataclasses.replace(
        capture,
        scene=dataclasses.replace(capture.scene, environment=(0.0, 0.0, 0.0)),  # black around
        views=[base, dataclasses.replace(base, name="moved", camera=moved)],
    )
    material = build_material({"type": "oren_nayar", "reflectance": [0.5] * 3, "sigma": 0.3})
    renderer = Renderer(capture, material, resolve(material, ["oren_nayar.sigma"]), batch=batch)
    assert len(renderer.groups) == (1 if batch else 2)
    images = renderer.render(np.asarray([0.3], np.float32), 0, 256).reshape(2, height, width, 3)
    for image in images:  # the sphere in view, whole: nothing lit on the border
        border = np.concatenate([image[[0, -1]].ravel(), image[:, [0, -1]].ravel()])
        assert border.max() < 1e-3 * image.max()
    centred, shifted = (_centroid(image) for image in images)
    np.testing.assert_allclose(shifted - centred, shift, atol=0.05)
