"""Scene geometry: the procedural cup, OBJ checks (UVs, normals, winding), far objects."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
from scene_tables import CUBE_FACES, cube_obj, scene_table

from captures import CaptureError, parse_scene
from captures.geometry import CupShape, check_obj_has_uvs, cup_mesh, cup_profile
from captures.images import write_image
from captures.scene import EnvMap, ObjFile


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


def test_a_cup_of_too_many_segments_is_refused():
    """A cup's segments are bounded (1e8 asked for 97 GiB: an internal MemoryError)."""
    from captures.schema import MAX_CUP_SEGMENTS

    table = scene_table(geometry={"type": "cup", "segments": 10**8})
    with pytest.raises(CaptureError, match=f"segments.*{MAX_CUP_SEGMENTS}"):
        parse_scene(table, Path("s.toml"))


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


def test_obj_and_envmap_paths_resolve_against_the_file(tmp_path):
    (tmp_path / "m.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n")
    write_image(tmp_path / "sky.exr", np.ones((4, 8, 3), np.float32))
    scene = parse_scene(
        scene_table(geometry="m.obj", environment={"type": "envmap", "file": "sky.exr"}),
        tmp_path / "s.toml",
    )
    assert scene.geometry == ObjFile(tmp_path / "m.obj")
    assert scene.environment == EnvMap(tmp_path / "sky.exr", 1.0)


def test_peer_scene_is_an_obj(shared_data):
    from captures import load_peer_scene

    scene = load_peer_scene(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    assert isinstance(scene.geometry, ObjFile) and scene.geometry.path.name == "mesh.obj"
    check_obj_has_uvs(scene.geometry.path)
    assert Path(scene.meta["images"][0]).exists()


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
