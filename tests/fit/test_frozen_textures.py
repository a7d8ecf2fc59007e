"""Frozen renders with a texture free: replayed after the texels change, primal images and
reverse-pass gradients equal what the same renders give unfrozen (a mask's texels inside the
`fbm` texture, a pigment's under the glaze; perspective views in one `batch` sensor,
orthographic ones each their own sensor)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from captures.capture import Capture, View
from captures.scene import Camera
from fit.config import load_render_config
from fit.material import build_material, resolve
from fit.material.textures import with_free_textures
from fit.render import Renderer

ROOT = Path(__file__).resolve().parents[2]
STACK = {
    "type": "layered",
    "layers": [
        {"name": "clay", "type": "oren_nayar", "reflectance": [0.8, 0.75, 0.7]},
        {
            "name": "glaze",
            "type": "glaze",
            "pigment": [0.1, 0.22, 0.55],
            "mask": {"threshold": 0.3, "softness": 0.05, "scale": 4},
        },
    ],
}
#: Calls of each pass: recordings, then replays.
STEPS = 6
GLAZE = {"type": "glaze", "pigment": [0.4, 0.4, 0.4], "roughness": 0.2, "ior": 1.5}


def capture(kind: str) -> Capture:
    """Two 24x18 views of the sphere (no photographs: only renders are compared); `kind`
    "thin-lens" a perspective camera with an aperture (a sensor each, rebuilt in recordings)."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    lens = {"aperture_radius": 0.05} if kind == "thin-lens" else {}
    kind = "perspective" if kind == "thin-lens" else kind
    cameras = tuple(
        Camera(
            (5 * np.sin(a), -5 * np.cos(a), 0.5), (0, 0, 0), (0, 0, 1), 30.0, 24, 18, kind, **lens
        )
        for a in np.radians([0, 150])
    )
    scene = dataclasses.replace(cfg.scene, cameras=cameras, environment=(0.5, 0.5, 0.5))
    blank = np.zeros((18, 24, 3), np.float32)
    views = [View(f"v{i}", blank, np.ones((18, 24), np.float32), c) for i, c in enumerate(cameras)]
    return Capture(scene, views)


@pytest.mark.parametrize(
    ("kind", "table", "key", "shape"),
    [
        ("perspective", STACK, "glaze.mask.texture", (8, 4)),
        ("orthographic", GLAZE, "glaze.pigment", (6, 4)),
        ("thin-lens", STACK, "glaze.mask.texture", (5, 3)),
    ],
    ids=["mask-in-fbm-perspective", "pigment-orthographic", "mask-thin-lens-odd-size"],
)
def test_frozen_renders_follow_the_texels(tmp_path, kind, table, key, shape):
    material = with_free_textures(build_material(table, tmp_path / "m.toml"), {key: shape})
    keys = [key, "glaze.roughness"] if "roughness" in table else [key, "glaze.mask.threshold"]
    free = resolve(material, keys)
    cap = capture(kind)
    frozen = Renderer(cap, material, free)
    rng = np.random.default_rng(3)
    cotangent = rng.standard_normal(frozen.size).astype(np.float32)
    steps = []
    for step in range(STEPS):
        texels = rng.uniform(0.1, 0.9, free[0].size)
        values = np.concatenate([texels, [0.25 + 0.02 * step]]).astype(np.float32)
        image = frozen.render(values, step, 4)
        steps.append((values, image, frozen.vjp(values, step, 4, cotangent)))
    for group in frozen.groups:  # replayed, not fallen back to plain renders (Dr.Jit records
        for fn in (group.primal, group.reverse):  # a function two or three times per sensor)
            assert fn.frozen is not None and fn.frozen.n_recordings <= 3 * len(group.parts)
    # the unfrozen renders afterwards: a scene of orthographic cameras alive beside a recording
    # makes it fail (`fit.render.renderer._Frozen`)
    plain = Renderer(cap, material, free, freeze=False)
    for step, (values, image, grad) in enumerate(steps):
        np.testing.assert_allclose(image, plain.render(values, step, 4), atol=1e-5)
        want = plain.vjp(values, step, 4, cotangent)
        # texels, then the scalar; a frozen pass's scalar gradient may drift by 0.1 % from the
        # plain one, with or without textures, after other tests' scenes (stale texels: 2-100 %)
        n = free[0].size
        assert np.abs(grad[:n] - want[:n]).max() <= 1e-2 * np.abs(want[:n]).max(), step
        assert grad[n] == pytest.approx(want[n], rel=1e-2), step
        assert np.abs(want[:n]).max() > 0  # the texels do have a gradient
    assert np.abs(steps[-1][1] - steps[-2][1]).max() > 0.01  # the texels change the image
