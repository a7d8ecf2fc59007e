"""The scene schema's errors name the file and the key; a TOML with a byte-order mark reads."""

from __future__ import annotations

import pytest
from scene_tables import calibrated, one_camera, scene_table

from captures import CaptureError, parse_scene


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


def test_a_toml_saved_with_a_byte_order_mark_reads(tmp_path):
    """Windows editors save UTF-8 with an invisible byte-order mark, which TOML rejects at line 1,
    column 1: it is read as the file's text."""
    from captures.schema import load_toml

    (tmp_path / "s.toml").write_bytes(b"\xef\xbb\xbf" + b'[scene]\ngeometry = "sphere"\n')
    assert load_toml(tmp_path / "s.toml") == {"scene": {"geometry": "sphere"}}
