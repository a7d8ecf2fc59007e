"""Scene lights and environments: colour temperature, power, kinds, lights that light nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scene_tables import cube_obj, scene_table

from captures import CaptureError, parse_scene
from captures.color import blackbody_rgb, planckian_xy
from captures.images import write_image
from captures.scene import Cup, EnvMap, PointLight, RectLight, Sphere

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def test_blackbody():
    assert planckian_xy(6500) == pytest.approx((0.3135, 0.3237), abs=5e-4)  # CIE tables
    assert planckian_xy(2700) == pytest.approx((0.4599, 0.4106), abs=1e-3)
    for t in (2700, 3200, 5000, 6500, 10000):
        assert LUMINANCE @ blackbody_rgb(t) == pytest.approx(1.0, rel=0.01)
    r, g, b = blackbody_rgb(3200)
    assert r > g > b
    assert np.ptp(blackbody_rgb(6500)) < 0.07  # near D65: nearly neutral
    with pytest.raises(ValueError, match="outside"):
        blackbody_rgb(1000)


def test_rectangle_light_by_power_and_temperature(tmp_path):
    scene = parse_scene(scene_table(), tmp_path / "s.toml")
    (light,) = scene.lights
    assert isinstance(light, RectLight)
    radiance = np.array(light.radiance)
    expected = 10.0 * np.array(blackbody_rgb(3200)) / (math.pi * 0.5 * 0.2)
    np.testing.assert_allclose(radiance, expected, rtol=1e-9)
    u, v, n = (np.array(x) for x in (light.u_axis, light.v_axis, light.emit_direction))
    np.testing.assert_allclose(n, -np.array([2, -2, 2]) / np.linalg.norm([2, -2, 2]), atol=1e-12)
    np.testing.assert_allclose(np.cross(u, v), -n, atol=1e-12)  # the peers' convention


def test_other_lights_and_cameras(tmp_path):
    scene = parse_scene(
        scene_table(
            geometry={"type": "cup", "height": 0.1, "handle": False},
            cameras=[
                {
                    "type": "orthographic",
                    "origin": [0, -3, 0],
                    "target": [0, 0, 0],
                    "ortho_width": 0.3,
                    "width": 8,
                    "height": 8,
                },
                {
                    "origin": [0, -3, 0],
                    "target": [0, 0, 0],
                    "fov_x_deg": 30,
                    "width": 8,
                    "height": 8,
                    "aperture_radius": 0.01,
                },
            ],
            lights=[
                {
                    "type": "point",
                    "position": [0, 0, 3],
                    "power": 4 * math.pi,
                    "color": [1, 0.5, 0.25],
                },
                {"type": "directional", "direction": [0, 0, -2], "irradiance": 3.0},
            ],
            environment={"type": "constant", "radiance": [0.1, 0.1, 0.1]},
        ),
        tmp_path / "s.toml",
    )
    assert isinstance(scene.geometry, Cup) and not scene.geometry.shape.handle
    assert scene.cameras[0].kind == "orthographic" and scene.cameras[1].aperture_radius == 0.01
    point, sun = scene.lights
    assert isinstance(point, PointLight) and point.intensity == pytest.approx((1.0, 0.5, 0.25))
    assert sun.direction == pytest.approx((0, 0, -1)) and sun.irradiance == (3.0, 3.0, 3.0)
    assert scene.environment == (0.1, 0.1, 0.1)
    assert isinstance(parse_scene(scene_table(), tmp_path / "s.toml").geometry, Sphere)


def test_a_light_that_lights_nothing_is_refused_by_its_field(tmp_path):
    """A rectangle whose emitting side faces away from the whole object (emit_direction given
    as +(u_axis x v_axis): a synth render 3.4x darker, its key light lighting nothing), a black
    colour (the error named power), a black environment map: each refused, naming the field.
    A light with the object partly ahead of it is kept."""
    away = {"center": [0, 0, 3], "u_axis": [1, 0, 0], "v_axis": [0, -1, 0], "size": [1, 1]}
    away |= {"emit_direction": [0, 0, 1], "radiance": 5.0}
    with pytest.raises(CaptureError, match=r"s.toml: scene.lights\[1\]: emits towards .* away"):
        parse_scene(scene_table(lights=[scene_table()["lights"][0], away]), tmp_path / "s.toml")
    sideways = away | {"center": [0, 0, 1.5], "emit_direction": [1, 0, 0]}
    sideways |= {"u_axis": [0, 1, 0], "v_axis": [0, 0, 1]}
    parse_scene(scene_table(lights=[sideways]), tmp_path / "s.toml")  # the object half ahead
    black = scene_table()["lights"][0] | {"color": [0, 0, 0]}
    del black["temperature"]
    with pytest.raises(CaptureError, match=r"lights\[0\]\.color.* is black"):
        parse_scene(scene_table(lights=[black]), tmp_path / "s.toml")
    write_image(tmp_path / "sky.exr", np.zeros((4, 8, 3), np.float32))
    dark = scene_table(lights=[], environment={"type": "envmap", "file": "sky.exr"})
    with pytest.raises(CaptureError, match="is black everywhere: it lights nothing"):
        parse_scene(dark, tmp_path / "s.toml")


@pytest.mark.parametrize(
    "huge, said",
    [
        (1e200, r"u_axis\[0\]: got 1e\+200; should be less than"),
        (math.inf, r"u_axis\[0\]: got inf"),
    ],
)
def test_a_light_frame_of_huge_axes_is_one_line(tmp_path, huge, said):
    """An axis of 1e200 (found by the fuzzer: its products overflowed, a RuntimeWarning that the
    test run makes an error) is refused by its size, as every number past 1e12 is."""
    light = {"center": [0, 0, 3], "u_axis": [huge, 0, 0], "v_axis": [0, 1, 0], "size": [1, 1]}
    light |= {"emit_direction": [0, 0, -1], "radiance": 5.0}
    with pytest.raises(CaptureError, match=said):
        parse_scene(scene_table(lights=[light]), tmp_path / "s.toml")


@pytest.mark.parametrize(
    "geometry, light, refused",
    [
        ("sphere", {"center": [0.2, 0.1, 0], "target": [0, 3, 0], "size": [0.1, 0.1]}, "center"),
        ("sphere", {"type": "point", "position": [0.0, 0.0, 0.5]}, "position"),
        ("sphere", {"type": "point", "position": [0.0, 0.0, 1.5]}, None),
        ("sphere", {"type": "directional", "direction": [0, 0, -1]}, None),
        ("cube.obj", {"type": "point", "position": [0.5, -0.5, 0.2]}, "position"),
        ("cube.obj", {"type": "point", "position": [0.0, -1.2, 0.0]}, None),
        ("cup", {"type": "point", "position": [0.0, -0.0355, 0.05]}, "position"),  # its wall
        ("cup", {"type": "point", "position": [0.0, 0.0, 0.05]}, None),  # its hollow
    ],
)
def test_a_light_inside_the_object_is_refused(tmp_path, geometry, light, refused):
    """A light inside the object lights only its inside (the object renders black): refused by
    its field's name, as a camera there is; outside it (in a cup's hollow too), kept."""
    if geometry == "cube.obj":
        cube_obj(tmp_path / "cube.obj", flip=(0, 2))  # wound unevenly: the count decides
    light = {"power": 10.0, "temperature": 3200, **light}
    if light.get("type") == "directional":
        light = {k: v for k, v in light.items() if k != "power"} | {"irradiance": 1.0}
    table = scene_table(geometry=geometry, lights=[scene_table()["lights"][0], light])
    if refused is None:
        parse_scene(table, tmp_path / "s.toml")
        return
    with pytest.raises(
        CaptureError, match=rf"scene.lights\[1\].{refused} .* is inside the object.*the light"
    ):
        parse_scene(table, tmp_path / "s.toml")


@pytest.mark.parametrize("names", [("R", "G"), ("R", "G", "B", "A", "Z"), ("Y", "A")])
def test_an_image_of_other_channels_is_refused_by_name(tmp_path, names):
    """Mitsuba's bitmap reads grey, grey and alpha, RGB and RGBA: a 2-channel (R, G) environment
    map had ended in an internal error inside the renderer; now it is refused with the fix."""
    import OpenImageIO as oiio

    path = tmp_path / "sky.exr"
    spec = oiio.ImageSpec(8, 4, len(names), "float")
    spec.channelnames = names
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ones((4, 8, len(names)), np.float32))
    out.close()
    table = scene_table(environment={"type": "envmap", "file": "sky.exr"})
    if names == ("Y", "A"):
        assert isinstance(parse_scene(table, tmp_path / "s.toml").environment, EnvMap)
        return
    with pytest.raises(CaptureError, match=rf"sky.exr' has {len(names)} channels .* RGBA \(4\)"):
        parse_scene(table, tmp_path / "s.toml")
