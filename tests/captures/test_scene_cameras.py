"""Scene cameras: principal points, thin lenses, fields of view, a camera inside the object."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scene_tables import CUBE_FACES, calibrated, cube_obj, scene_table

from captures import CaptureError, parse_scene


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
