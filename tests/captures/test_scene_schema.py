"""Scene descriptions: the procedural cup, colour temperature, OBJ checks, the TOML schema."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from captures import CaptureError, parse_scene
from captures.color import blackbody_rgb, planckian_xy
from captures.geometry import CupShape, check_obj_has_uvs, cup_mesh, cup_profile
from captures.images import write_image
from captures.scene import Cup, EnvMap, ObjFile, PointLight, RectLight, Sphere

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def test_cup_mesh_is_sound():
    shape = CupShape()
    mesh = cup_mesh(shape)
    n = len(mesh.positions)
    assert mesh.faces.min() >= 0 and mesh.faces.max() < n
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, rtol=1e-6)
    assert mesh.uvs.min() >= 0 and mesh.uvs.max() <= 1
    # no degenerate triangles
    p = mesh.positions
    area = np.linalg.norm(
        np.cross(
            p[mesh.faces[:, 1]] - p[mesh.faces[:, 0]], p[mesh.faces[:, 2]] - p[mesh.faces[:, 0]]
        ),
        axis=1,
    )
    assert area.min() > 0
    # vertex normals agree with the faces' winding (outward)
    face_n = np.cross(
        p[mesh.faces[:, 1]] - p[mesh.faces[:, 0]], p[mesh.faces[:, 2]] - p[mesh.faces[:, 0]]
    )
    vertex_n = mesh.normals[mesh.faces].mean(axis=1)
    assert np.mean(np.sum(face_n * vertex_n, axis=1) > 0) > 0.999
    # size: the mesh spans the declared dimensions
    assert p[:, 2].min() == pytest.approx(0.0, abs=1e-9)
    assert p[:, 2].max() == pytest.approx(shape.height + shape.wall / 2, rel=0.02)


def test_cup_profile_is_smooth_and_has_thickness():
    shape = CupShape()
    profile = cup_profile(shape)
    steps = np.diff(profile, axis=0)
    angles = np.arctan2(steps[:, 1], steps[:, 0])
    turn = np.abs((np.diff(angles) + np.pi) % (2 * np.pi) - np.pi)
    assert turn.max() < 0.35  # G1: no corner sharper than ~20 degrees between segments
    # wall thickness: the profile crosses mid height twice (outer, inner wall), `wall` apart
    mid = shape.height / 2
    crossings = [
        r0 + (r1 - r0) * (mid - z0) / (z1 - z0)
        for (r0, z0), (r1, z1) in itertools.pairwise(profile)
        if (z0 - mid) * (z1 - mid) < 0
    ]
    assert len(crossings) == 2
    assert abs(crossings[0] - crossings[1]) == pytest.approx(shape.wall, rel=0.1)


def test_cup_body_tiles_across_the_seam():
    mesh = cup_mesh(CupShape(handle=False, segments=16))
    u0, u1 = mesh.uvs[:, 0] == 0, mesh.uvs[:, 0] == 1
    np.testing.assert_allclose(mesh.positions[u0], mesh.positions[u1], atol=1e-12)
    np.testing.assert_allclose(mesh.uvs[u0, 1], mesh.uvs[u1, 1])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"wall": 0.03}, "wall"),
        ({"fillet": 0.0}, "fillet"),
        ({"base": 0.001}, "base"),
        ({"segments": 4}, "segments"),
    ],
)
def test_bad_cup_shapes(kwargs, message):
    with pytest.raises(ValueError, match=message):
        CupShape(**kwargs)


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


def test_obj_needs_uvs(tmp_path):
    without = tmp_path / "plain.obj"
    without.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(
        CaptureError, match=r"plain.obj: the OBJ has no texture coordinates on 1 of 1"
    ):
        check_obj_has_uvs(without)
    with_uv = tmp_path / "uv.obj"
    with_uv.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    check_obj_has_uvs(with_uv)
    with pytest.raises(CaptureError, match="no such OBJ"):
        check_obj_has_uvs(tmp_path / "none.obj")


def scene_table(**over):
    table = {
        "geometry": "sphere",
        "cameras": [
            {"origin": [0, -3, 0], "target": [0, 0, 0], "fov_x_deg": 40, "width": 8, "height": 8}
        ],
        "lights": [
            {
                "center": [2, -2, 2],
                "target": [0, 0, 0],
                "size": [0.5, 0.2],
                "power": 10.0,
                "temperature": 3200,
            }
        ],
    }
    table.update(over)
    return table


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


def test_obj_and_envmap_paths_resolve_against_the_file(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n")
    write_image(tmp_path / "sky.exr", np.ones((4, 8, 3), np.float32))
    scene = parse_scene(
        scene_table(geometry="m.obj", environment={"type": "envmap", "file": "sky.exr"}),
        tmp_path / "s.toml",
    )
    assert scene.geometry == ObjFile(tmp_path / "m.obj")
    assert scene.environment == EnvMap(tmp_path / "sky.exr", 1.0)


def rect_light(**extra) -> dict:
    """A scene table with one rectangle light facing the origin, plus `extra` keys."""
    return {"lights": [{"center": [1, 1, 1], "target": [0, 0, 0], "size": [1, 1], **extra}]}


@pytest.mark.parametrize(
    "change, message",
    [
        ({"geometry": "cube"}, "scene.geometry: got 'cube'; give sphere, cup or the name"),
        ({"geometry": "cube.obj"}, "scene.geometry.file: 'cube.obj' does not exist"),
        ({"geometry": {"type": "cup", "wall": 0.5}}, "scene.geometry: cup: wall = 0.5"),
        ({"cameras": []}, "scene.cameras: got []; should have at least 1 item"),
        (
            {
                "cameras": [
                    {
                        "origin": [0, 0, 0],
                        "target": [0, 0, 0],
                        "fov_x_deg": 40,
                        "width": 8,
                        "height": 8,
                    }
                ]
            },
            "equals origin",
        ),
        (
            {
                "cameras": [
                    {
                        "type": "orthographic",
                        "origin": [0, -1, 0],
                        "target": [0, 0, 0],
                        "width": 8,
                        "height": 8,
                    }
                ]
            },
            "scene.cameras[0].ortho_width: missing; add it",
        ),
        (
            rect_light(),
            "needs exactly one of radiance or power",
        ),
        (
            rect_light(power=1, radiance=[1, 1, 1]),
            "needs exactly one of radiance or power",
        ),
        (
            rect_light(power=1, temperature=500),
            "scene.lights[0].temperature: 500 K is outside",
        ),
        (
            {"lights": [{"type": "spot", "position": [0, 0, 1]}]},
            "scene.lights[0].type: got 'spot'; choose one of rectangle, point, directional",
        ),
        (
            rect_light(power=1, colour=[1, 1, 1]),
            "scene.lights[0].colour: unknown key; known: color, temperature, type",
        ),
        ({"lights": [], "environment": [0, 0, 0]}, "the scene has no light"),
        ({"integrator": "bdpt"}, "scene.integrator: got 'bdpt'; choose one of prb, path"),
    ],
)
def test_scene_errors_name_the_key(tmp_path, change, message):
    with pytest.raises(CaptureError) as err:
        parse_scene(scene_table(**change), tmp_path / "s.toml")
    assert message in str(err.value) and "s.toml" in str(err.value)


def test_peer_scene_is_an_obj(shared_data):
    from captures import load_peer_scene

    scene = load_peer_scene(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    assert isinstance(scene.geometry, ObjFile) and scene.geometry.path.name == "mesh.obj"
    check_obj_has_uvs(scene.geometry.path)
    assert Path(scene.meta["images"][0]).exists()
