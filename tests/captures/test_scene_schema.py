"""Scene descriptions: the procedural cup, colour temperature, OBJ checks, the TOML schema."""

from __future__ import annotations

import dataclasses
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


def test_a_cup_of_too_many_segments_is_refused():
    """A cup's segments are bounded (1e8 asked for 97 GiB: an internal MemoryError)."""
    from captures.schema import MAX_CUP_SEGMENTS

    table = scene_table(geometry={"type": "cup", "segments": 10**8})
    with pytest.raises(CaptureError, match=f"segments.*{MAX_CUP_SEGMENTS}"):
        parse_scene(table, Path("s.toml"))


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


def one_camera(**keys) -> dict:
    """A scene table's cameras: one camera of `keys`."""
    return {"cameras": [keys]}


def calibrated(**extra) -> dict:
    """A scene table with one 8x6 perspective camera, plus `extra` camera keys."""
    return one_camera(fov_x_deg=40, origin=[0, -4, 0], target=[0, 0, 0], width=8, height=6, **extra)


def test_a_principal_point_is_read_and_written_back(tmp_path):
    from captures.schema import camera_to_table

    scene = parse_scene(scene_table(**calibrated(principal_point=[4.75, 2])), tmp_path / "s.toml")
    (camera,) = scene.cameras
    assert camera.principal_point == (4.75, 2.0)
    assert camera.principal_offset() == pytest.approx((0.5 - 4.75 / 8, 0.5 - 2 / 6))
    table = camera_to_table(camera)
    assert table["principal_point"] == [4.75, 2.0]
    again = parse_scene(scene_table(cameras=[table]), tmp_path / "s.toml").cameras[0]
    assert again == camera
    # a downscaled camera keeps the point where it was on the scene: 8 px -> 3 (8/3 px each)
    small = camera.resized(3, 2)
    assert small.principal_point == pytest.approx((1.5 + 0.75 * 3 / 8, 1.0 - 1.0 * 3 / 8))


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
            one_camera(origin=[0, 0, 0], target=[0, 0, 0], fov_x_deg=40, width=8, height=8),
            "equals origin",
        ),
        (
            one_camera(type="orthographic", origin=[0, -1, 0], target=[0, 0, 0], width=8, height=8),
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
        ({"geometry": "scan.ply"}, "meshio convert mesh.ply mesh.obj"),
        (
            one_camera(origin=[0, 0, 4], target=[0, 0, 0], width=8, height=8),
            "scene.cameras[0].up: the default [0.0, 0.0, 1.0] is zero or along the viewing "
            "direction (origin to target); give up = [0, 1, 0]",
        ),
        (
            one_camera(
                origin=[0, -4, 0], target=[0, 0, 0], up=[0, 1, 0], fov_x_deg=40, width=8, height=8
            ),
            "scene.cameras[0].up: [0.0, 1.0, 0.0] is zero or along the viewing direction (origin "
            "to target); give up = [0, 0, 1]",
        ),
        (
            one_camera(type="thinlens", origin=[0, -4, 0], target=[0, 0, 0]),
            "scene.cameras[0].type: got 'thinlens'; a thin lens is type = \"perspective\" with "
            "aperture_radius",
        ),
        # a calibrated principal point: a pinhole's only, in this image's pixels, near its centre
        (
            calibrated(principal_point=[4.5, 3.5], aperture_radius=0.01),
            "scene.cameras[0].principal_point: applies to a pinhole camera only",
        ),
        (
            calibrated(principal_point=[0.52, 0.49]),  # normalised, not pixels
            "scene.cameras[0].principal_point: [0.52, 0.49] is 44% of the image from its centre "
            "[4, 3] (at most 25%): give it in pixels of this 8x6 image",
        ),
        (
            calibrated(principal_point=[4.5, 9.0]),  # pixels of a larger image
            "[4.5, 9] is 100% of the image from its centre",
        ),
        (calibrated(principal_point=[4.5]), "scene.cameras[0].principal_point"),
        (calibrated(principal_point=[4.5, float("nan")]), "scene.cameras[0].principal_point"),
        (
            calibrated(type="orthographic", ortho_width=1, principal_point=[4, 3]),
            "scene.cameras[0].fov_x_deg: does not apply",
        ),
        (
            one_camera(
                type="orthographic",
                origin=[0, -4, 0],
                target=[0, 0, 0],
                width=8,
                height=6,
                ortho_width=1,
                principal_point=[4, 3],
            ),
            "scene.cameras[0].principal_point: does not apply to type = 'orthographic'",
        ),
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


# A cube of side 2 about `offset`: 8 shared vertices, 6 quads wound outward (counter-clockwise
# seen from outside).
CUBE_FACES = [
    (1, 2, 4, 3),  # -z ... each listed as 1-based indices of the corners below
    (5, 7, 8, 6),
    (1, 5, 6, 2),
    (3, 4, 8, 7),
    (1, 3, 7, 5),
    (2, 6, 8, 4),
]


def cube_obj(path, offset=(0.0, 0.0, 0.0), flip=(), normals=False):
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    lines = [f"v {x + offset[0]} {y + offset[1]} {z + offset[2]}" for x, y, z in corners]
    faces = [f[::-1] if i in flip else f for i, f in enumerate(CUBE_FACES)]
    if normals:  # one normal per face, its corners pointing at it
        for f in faces:
            n = np.sign(np.sum([corners[i - 1] for i in f], axis=0)).astype(int)
            lines.append(f"vn {n[0]} {n[1]} {n[2]}")
        lines += [f"f {' '.join(f'{i}//{k}' for i in f)}" for k, f in enumerate(faces, 1)]
    else:
        lines += [f"f {' '.join(map(str, f))}" for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_the_cube_is_wound_outward():
    """The fixture itself: each face's normal (by its winding) points away from the centre."""
    corners = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    for f in CUBE_FACES:
        p = corners[[i - 1 for i in f]]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        assert normal @ p.mean(axis=0) > 0


def test_a_mesh_without_normals_says_how_it_will_shade(tmp_path, caplog):
    """Without `vn` the renderer interpolates normals (a box renders rounded) and a face's front
    follows its winding (faces wound against their neighbours, or a whole mesh inside out, show
    their black backs): each is one warning naming the file and the fix, kept with the scene."""
    from captures.geometry import check_obj

    plain = cube_obj(tmp_path / "cube.obj")
    (warning,) = check_obj(plain).warnings
    assert "cube.obj: has no vertex normals" in warning and "rounds the 12 sharper" in warning
    assert "face_normals = true" in warning
    assert "UV island" not in warning  # it has none (the note read oddly there)
    assert check_obj(plain, face_normals=True).warnings == ()
    assert check_obj(cube_obj(tmp_path / "vn.obj", normals=True)).warnings == ()

    # two neighbouring faces flipped: their 4 + 4 edges, the one they share counted twice
    mixed = check_obj(cube_obj(tmp_path / "mixed.obj", flip=(0, 3))).warnings
    assert any("6 of its 12 shared edges join faces wound in opposite" in w for w in mixed)
    (flat,) = check_obj(tmp_path / "mixed.obj", face_normals=True).warnings
    assert "with face_normals a face's front" in flat and "with normals" not in flat
    inside_out = check_obj(cube_obj(tmp_path / "in.obj", flip=range(6)), face_normals=True)
    assert len(inside_out.warnings) == 1 and "1 of its closed parts" in inside_out.warnings[0]
    # two closed parts, the second inside out: their volumes would cancel in one sum
    good, bad = (tmp_path / "in.obj").read_text(), (tmp_path / "cube.obj").read_text()
    two = [line for line in good.splitlines() if line.startswith("v ")]
    two += [" ".join(["v", *(str(float(x) + 5) for x in line.split()[1:])]) for line in two]
    two += [line for line in bad.splitlines() if line.startswith("f ")]
    two += [
        "f " + " ".join(str(int(i) + 8) for i in line.split()[1:])
        for line in good.splitlines()
        if line.startswith("f ")
    ]
    (tmp_path / "two.obj").write_text("\n".join(two) + "\n")
    (part,) = check_obj(tmp_path / "two.obj", face_normals=True).warnings
    assert "1 of its closed parts are wound inside out" in part
    # a UV seam on every edge (each face its own island): Mitsuba splits the vertices there
    islands = [line for line in bad.splitlines() if line.startswith("v ")]
    islands += ["vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1"]
    islands += [
        "f " + " ".join(f"{i}/{k + 1}" for k, i in enumerate(line.split()[1:]))
        for line in bad.splitlines()
        if line.startswith("f ")
    ]
    (tmp_path / "islands.obj").write_text("\n".join(islands) + "\n")
    assert check_obj(tmp_path / "islands.obj").warnings == ()
    assert check_obj(cube_obj(tmp_path / "in_vn.obj", flip=range(6), normals=True)).warnings == ()
    # a "triangle soup" (every face its own corners) is one object where its corners meet: wound
    # inside out it is warned (each face was an open part of its own: nothing said)
    for name, source in (("soup.obj", bad), ("soup_in.obj", good)):
        points = [line for line in source.splitlines() if line.startswith("v ")]
        faces = [line.split()[1:] for line in source.splitlines() if line.startswith("f ")]
        soup = [points[int(i) - 1] for face in faces for i in face]  # each corner its own
        first = np.cumsum([0] + [len(face) for face in faces])
        soup += [
            "f " + " ".join(str(first[k] + j + 1) for j in range(len(face)))
            for k, face in enumerate(faces)
        ]
        (tmp_path / name).write_text("\n".join(soup) + "\n")
    assert check_obj(tmp_path / "soup.obj").warnings == ()  # no shared vertex: none rounded
    (soup_in,) = check_obj(tmp_path / "soup_in.obj").warnings
    assert "1 of its closed parts are wound inside out" in soup_in

    caplog.set_level("WARNING")
    scene = parse_scene(scene_table(geometry="cube.obj"), tmp_path / "s.toml")
    assert scene.geometry.warnings == (warning,) and warning in caplog.text
    flat = parse_scene(
        scene_table(geometry={"type": "obj", "file": "cube.obj", "face_normals": True}),
        tmp_path / "s.toml",
    )
    assert flat.geometry.face_normals and flat.geometry.warnings == ()


def test_smooth_meshes_without_normals_are_not_warned(tmp_path):
    """Finely divided smooth surfaces written without normals (a UV sphere, the procedural cup)
    have no sharp edges and are wound alike: no warning."""
    from captures.geometry import check_obj

    def write(path, positions, faces):
        lines = [f"v {x} {y} {z}" for x, y, z in positions]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
        path.write_text("\n".join(lines) + "\n")
        return path

    theta, phi = np.meshgrid(np.linspace(0, np.pi, 17), np.linspace(0, 2 * np.pi, 33)[:-1])
    grid = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    index = np.arange(grid.shape[0] * grid.shape[1]).reshape(grid.shape[:2])
    nxt = np.roll(index, -1, axis=0)
    a, b = index[:, :-1].ravel(), nxt[:, :-1].ravel()
    c, d = nxt[:, 1:].ravel(), index[:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])
    sphere = write(tmp_path / "sphere.obj", grid.reshape(-1, 3), faces)
    assert check_obj(sphere).warnings == ()
    cup = cup_mesh(CupShape())
    assert check_obj(write(tmp_path / "cup.obj", cup.positions, cup.faces)).warnings == ()


@pytest.mark.parametrize("offset, far", [(1e2, False), (1e5, True), (4e6, True)])
def test_an_object_far_from_the_origin_is_refused(tmp_path, offset, far):
    """float32 positions tear a surface 1e4 radii from the origin: refused with the fix."""
    cube_obj(tmp_path / "cube.obj", offset=(offset, -offset, 0.0))
    camera = {"origin": [offset, -offset - 6, 0], "target": [offset, -offset, 0]}
    table = scene_table(geometry="cube.obj")
    table["cameras"][0].update(camera)
    table["lights"][0].update(center=[offset + 2, -offset - 2, 2], target=[offset, -offset, 0])
    if not far:
        parse_scene(table, tmp_path / "s.toml")
        return
    with pytest.raises(CaptureError, match=r"s.toml: scene.geometry: the object .* reaches"):
        parse_scene(table, tmp_path / "s.toml")
    sphere = scene_table(geometry={"type": "sphere", "center": [offset, 0, 0], "radius": 1.0})
    with pytest.raises(CaptureError, match="move the scene to the origin"):
        parse_scene(sphere, tmp_path / "s.toml")


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


def test_an_output_path_that_is_not_utf8_is_refused_by_name(tmp_path):
    """A name whose bytes are not UTF-8 (Python holds them escaped) is refused before any work,
    its bytes shown escaped: the image and JSON writers and the report take text (an internal
    error once the work was done)."""
    import os

    from captures.errors import InputError
    from captures.files import check_output

    bad = Path(os.fsdecode(os.fsencode(tmp_path) + b"/out\xff.png"))
    with pytest.raises(InputError, match=r"--out .*out\\xff\.png: the path is not UTF-8"):
        check_output(bad, "--out")
    assert check_output(tmp_path / "out-\u00e9.png", "--out").name == "out-\u00e9.png"


def test_input_files_whose_path_is_not_utf8_are_refused_by_name(tmp_path):
    """Images, masks, RAWs and meshes under a name that is not UTF-8 are refused in one line
    with the bytes escaped (OpenImageIO's open raised a TypeError: an internal error)."""
    import os

    from captures.geometry import check_obj
    from captures.images import image_problem, read_image, read_linear
    from captures.raw import read_raw

    folder = Path(os.fsdecode(os.fsencode(tmp_path) + b"/caf\xe9"))
    folder.mkdir()
    write_image(tmp_path / "v.png", np.full((4, 4, 3), 0.5, np.float32))  # its writer: no
    (tmp_path / "v.png").rename(folder / "v.png")
    cube_obj(folder / "cube.obj")
    for read in (read_image, lambda p: read_linear(p, "srgb"), read_raw):
        with pytest.raises(CaptureError, match=r"caf\\xe9/v.png: the path is not UTF-8"):
            read(folder / "v.png")
    with pytest.raises(CaptureError, match=r"caf\\xe9/cube.obj: the path is not UTF-8"):
        check_obj(folder / "cube.obj")
    assert "not a UTF-8 path" in image_problem(folder / "v.png")


def test_an_output_folder_names_only_whole_files_as_its_own(tmp_path):
    """`--force` replaces a folder whole: only files its main file names, as whole names, are
    the tool's (a `data.exr` reference does not make a user's `a.exr` the export's)."""
    from captures.files import foreign_entries

    (tmp_path / "material.xml").write_text(
        '<string name="filename" value="data.exr"/>\n<string value="textures/glaze.mask.exr"/>'
    )
    for name in ("data.exr", "a.exr", "glaze.mask.exr", "mask.exr", "notes.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "meshes").mkdir()
    found = foreign_entries(tmp_path, tmp_path / "material.xml")
    assert found == ["a.exr", "mask.exr", "meshes", "notes.txt"]


def test_an_atomic_file_is_on_disk_before_its_name_points_at_it(tmp_path, monkeypatch):
    """A file written through `atomic_path` is synced before the rename (a power cut after the
    rename left an empty file on filesystems that delay allocation); an error leaves neither the
    file nor its temporary."""
    import os

    from captures.files import write_text

    order = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (order.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(
        os, "replace", lambda a, b: (order.append("replace"), real_replace(a, b))[1]
    )
    write_text(tmp_path / "summary.json", "{}")
    assert order == ["fsync", "replace"] and (tmp_path / "summary.json").read_text() == "{}"
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(5, "I/O error")))
    with pytest.raises(OSError, match="I/O error"):
        write_text(tmp_path / "preset.toml", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_a_toml_saved_with_a_byte_order_mark_reads(tmp_path):
    """Windows editors save UTF-8 with an invisible byte-order mark, which TOML rejects at line 1,
    column 1: it is read as the file's text."""
    from captures.schema import load_toml

    (tmp_path / "s.toml").write_bytes(b"\xef\xbb\xbf" + b'[scene]\ngeometry = "sphere"\n')
    assert load_toml(tmp_path / "s.toml") == {"scene": {"geometry": "sphere"}}


@pytest.mark.parametrize("flip", [(), tuple(range(6)), (0, 2)])
@pytest.mark.parametrize(
    "geometry, origin, refused",
    [
        ("sphere", [0, 0.5, 0], True),
        ("sphere", [0, -3, 0], False),
        ("cube.obj", [0.5, 0.5, 0.2], True),  # inside the cube, whichever way it is wound
        ("cube.obj", [0, -1.2, 0], False),  # inside its bounding sphere, outside the cube
        ("cube.obj", [0.999, -1.001, 0.999], False),  # at a corner, just outside
        ("cup", [0.0, 0.0, 0.05], False),  # in the cup's hollow: outside its wall
        ("cup", [0.0, -0.0355, 0.05], True),  # in its wall, halfway up
        ("cup", [0.0, -0.6, 0.05], False),
    ],
)
def test_a_camera_inside_the_object_is_refused(tmp_path, geometry, origin, refused, flip):
    """A camera whose origin is inside the object sees its inside (units or axes mixed up): refused
    by name (rendered its back faces without a word). Outside it, however close, it is kept; a
    cube with two faces wound against the others (its winding number spoilt) is not refused
    from outside, and from inside it is (the cube is closed: the count of crossings decides; the
    winding number alone had let that camera through)."""
    if geometry == "cube.obj":
        cube_obj(tmp_path / "cube.obj", flip=flip)
    elif flip:
        return
    table = scene_table(geometry=geometry)
    table["cameras"][0].update(origin=origin, target=[0.0, 3.0, 0.05])
    if not refused:
        parse_scene(table, tmp_path / "s.toml")
        return
    with pytest.raises(CaptureError, match=r"s.toml: scene.cameras\[0\].origin .* is inside the"):
        parse_scene(table, tmp_path / "s.toml")


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


def test_winding_numbers_of_open_and_closed_meshes():
    """About 1 inside a closed mesh (-1 wound inward), 0 outside; an open sheet below 1/2 from
    anywhere, so a camera over a normal map's height field is never taken as inside."""
    from captures.geometry import winding_numbers

    corners = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    triangles = np.array([(f[0], f[i], f[i + 1]) for f in CUBE_FACES for i in (1, 2)]) - 1
    points = np.array([[0, 0, 0], [0.9, -0.9, 0.9], [3, 0, 0], [0, 1.01, 0]])
    np.testing.assert_allclose(winding_numbers(corners, triangles, points), [1, 1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(
        winding_numbers(corners, triangles[:, ::-1], points), [-1, -1, 0, 0], atol=1e-9
    )
    from captures.geometry import crossings

    counts = crossings(corners, triangles, points)
    assert counts[:2].tolist() == [[1, 1, 1]] * 2 and np.all(counts[2:] % 2 == 0)
    assert crossings(corners, triangles[:, ::-1], points[1]).tolist() == [[1, 1, 1]]
    sheet = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], float)
    near = winding_numbers(sheet, np.array([[0, 1, 2], [0, 2, 3]]), [[0, 0, 1e-3], [0, 0, -1]])
    assert np.all(np.abs(near) < 0.5) and abs(near[0]) > 0.49


def test_a_camera_between_two_parts_next_to_a_face_wound_wrong_is_kept(tmp_path):
    """Two unit cubes in one OBJ, the first's +x face wound against its neighbours: a camera
    between them, 0.01 off that face, is inside the mesh's box and its winding number is near 1
    (the flipped face subtends nearly half the sphere), but every ray crosses the faces an even
    number of times: kept. Inside the second cube: refused."""
    from captures.geometry import winding_numbers

    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    lines = [f"v {x} {y} {z}" for x, y, z in corners]
    lines += [f"v {x + 4} {y} {z}" for x, y, z in corners]
    positions = np.array([[float(w) for w in line.split()[1:]] for line in lines])
    faces = []
    for offset in (0, 8):
        for f in CUBE_FACES:
            quad = [i + offset for i in f]
            on_plus_x = all(corners[i - 1][0] == 1 for i in f)
            faces.append(quad[::-1] if offset == 0 and on_plus_x else quad)
    lines += ["f " + " ".join(map(str, f)) for f in faces]
    (tmp_path / "two.obj").write_text("\n".join(lines) + "\n")
    triangles = np.array([(f[0], f[i], f[i + 1]) for f in faces for i in (1, 2)]) - 1
    assert abs(winding_numbers(positions, triangles, [[1.01, 0.0, 0.0]])[0]) > 0.75
    table = scene_table(geometry="two.obj")
    table["cameras"][0].update(origin=[1.01, 0.0, 0.0], target=[1.01, -3.0, 0.0])
    parse_scene(table, tmp_path / "s.toml")
    table["cameras"][0].update(origin=[4.2, 0.1, 0.1], target=[4.2, -3.0, 0.1])
    with pytest.raises(CaptureError, match=r"scene.cameras\[0\].origin .* is inside the object"):
        parse_scene(table, tmp_path / "s.toml")


def test_an_off_centre_principal_point_widens_what_a_view_sees():
    """A principal point a quarter of the width off the centre shows 1.5x the tangent of half
    the field of view on one side: an object 31 degrees off the axis of a 40-degree camera is
    in that view (28.6 degrees, plus its own 3), not in a centred one's (27.2 at the corners).
    `sees` only refuses views that see nothing: it takes the farther side on both."""
    from captures.scene import Camera, sees

    camera = Camera((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), 40.0, 100, 100)
    off = np.radians(31.0)
    for side in (-1, 1):
        center = np.array([side * np.sin(off), np.cos(off), 0.0]) * 10.0
        radius = 10.0 * np.sin(np.radians(3.0))
        assert not sees(camera, center, radius)
        shifted = dataclasses.replace(camera, principal_point=(75.0, 50.0))
        assert sees(shifted, center, radius)


def test_a_camera_inside_the_bounding_sphere_is_not_refused_as_blind():
    """A long shelf under a small object (or a stray vertex far off) moves the bounding sphere's
    centre behind a camera that looks at the object: it sees it (it was refused as "does not see
    the object"); a camera outside the sphere looking away is still refused."""
    from captures.scene import Camera, sees

    center, radius = np.array([14.5, 0.0, 0.0]), 15.5  # a cube at 0 and a 31-m board
    camera = Camera((0.0, -3.0, 0.0), (-5.0, 0.0, 0.0), (0.0, 0.0, 1.0), 40.0, 64, 48)
    assert sees(camera, center, radius)
    away = Camera((0.0, -20.0, 0.0), (0.0, -40.0, 0.0), (0.0, 0.0, 1.0), 40.0, 64, 48)
    assert not sees(away, center, radius)


def test_closed_meshes_are_told_from_open_ones_whichever_way_they_are_wound():
    """Every edge (corners welded by position) shared by two triangles: the cube, wound either
    way or with faces apart (a triangle soup); without a face it is open."""
    from captures.geometry import closed

    corners = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    triangles = np.array([(f[0], f[i], f[i + 1]) for f in CUBE_FACES for i in (1, 2)]) - 1
    flipped = triangles.copy()
    flipped[:4] = flipped[:4, ::-1]
    soup = corners[triangles].reshape(-1, 3)
    assert closed(corners, triangles) and closed(corners, flipped)
    assert closed(soup, np.arange(len(soup)).reshape(-1, 3))
    assert not closed(corners, triangles[2:]) and not closed(corners, triangles[:0])


def test_a_folder_given_for_an_output_file_names_the_fix(tmp_path):
    """`--sheet some/folder`: it said "unsupported file type '(none)'"."""
    from captures.errors import InputError
    from captures.files import check_output

    with pytest.raises(InputError, match=r"--sheet .*: is a folder; give a file's name in it"):
        check_output(tmp_path, "--sheet", suffixes=(".png",))
    assert check_output(tmp_path / "s.png", "--sheet", suffixes=(".png",)) == tmp_path / "s.png"


@pytest.mark.parametrize(
    "extra, message",
    [
        ({"focus_distance": 3.0}, "scene.cameras[0].focus_distance: applies to a thin lens only"),
        (
            {"type": "orthographic", "ortho_width": 1, "focus_distance": 3.0},
            "scene.cameras[0].focus_distance: does not apply to type = 'orthographic'",
        ),
        ({"aperture_radius": 0.01, "focus_distance": 3.0}, None),
    ],
)
def test_a_focus_distance_needs_a_thin_lens(tmp_path, extra, message):
    """`focus_distance` on a pinhole or an orthographic camera was dropped without a word (a
    user who meant a thin lens got a pinhole); a thin lens's reads."""
    camera = {"origin": [0, -4, 0], "target": [0, 0, 0], "width": 8, "height": 6}
    camera |= {} if extra.get("type") else {"fov_x_deg": 40}
    table = scene_table(cameras=[camera | extra])
    if message is None:
        assert parse_scene(table, tmp_path / "s.toml").cameras[0].focus_distance == 3.0
        return
    with pytest.raises(CaptureError) as err:
        parse_scene(table, tmp_path / "s.toml")
    assert message in str(err.value)


@pytest.mark.parametrize(
    "camera, warned",
    [
        ({"fov_x_deg": 0.7}, True),
        ({"fov_x_deg": 40}, False),
        ({"type": "orthographic", "ortho_width": 0.7}, False),
    ],
)
def test_a_capture_cameras_field_of_view_in_radians_is_warned(tmp_path, caplog, camera, warned):
    """A capture.toml's camera with its field of view in radians is warned in the manifest's own
    field names, with the value in degrees; an orthographic camera has none to warn of."""
    import logging

    table = scene_table(
        cameras=[{"origin": [0, -4, 0], "target": [0, 0, 0], "width": 8, "height": 6} | camera]
    )
    with caplog.at_level(logging.WARNING):
        parse_scene(table, tmp_path / "s.toml")
    notes = [r.getMessage() for r in caplog.records if "in radians" in r.getMessage()]
    assert bool(notes) == warned
    if warned:
        assert "s.toml: scene.cameras[0].fov_x_deg = 0.7:" in notes[0]
        assert "give 40.11 (degrees)" in notes[0]
