"""Scene assembly: only what a config requires is built; every camera and light kind renders."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from captures import parse_scene
from fit.config import load_render_config
from fit.errors import ConfigError
from fit.material import material_dict
from fit.render import coverage_dict, load_scene, material_keys, render, scene_dict

ROOT = Path(__file__).resolve().parents[2]
CUP = ROOT / "configs" / "cup.toml"


def cup_material(edit=None) -> dict:
    doc = tomllib.loads(CUP.read_text())
    if edit:
        edit(doc["material"])
    return material_dict(doc["material"], CUP)


def built_keys(material: dict) -> set[str]:
    cfg = load_render_config(CUP)
    return set(material_keys(load_scene(scene_dict(cfg.scene, material, 0, 1))))


def layer(doc, name):
    return next(x for x in doc["layers"] if x["name"] == name)


def test_cup_builds_all_four_layers():
    keys = built_keys(cup_material())
    for key in (
        "bump",
        "clay.sigma",
        "glaze.roughness",
        "glaze.pigment_noise",
        "glaze.normal_noise",
        "glaze.mask.threshold",
        "lime.mask.softness",
        "stain.reflectance.value",
        "stain.mask.texture.data",
    ):
        assert key in keys, key


def test_disabled_layer_leaves_nothing_behind():
    def disable_stain(m):
        layer(m, "stain")["enabled"] = False

    keys = built_keys(cup_material(disable_stain))
    assert not [k for k in keys if k.startswith("stain.")]
    assert "lime.mask.threshold" in keys
    material = cup_material(disable_stain)
    assert material["layers"] == "clay,glaze,lime" and "stain_mask" not in material


def test_zero_options_are_not_built():
    def plain(m):
        m["bump"] = 0.0
        layer(m, "glaze")["pigment_noise"] = 0.0
        layer(m, "glaze")["normal_noise"] = 0.0

    keys = built_keys(cup_material(plain))
    assert "bump" not in keys
    assert not {"glaze.pigment_noise", "glaze.normal_noise"} & keys
    assert "pigment_noise_scale" not in cup_material(plain)["glaze"]


def test_a_stack_of_one_is_its_layer():
    def only_clay(m):
        for name in ("glaze", "lime", "stain"):
            layer(m, name)["enabled"] = False

    material = cup_material(only_clay)
    assert material["type"] == "oren_nayar"
    assert built_keys(material) == {"reflectance.value", "sigma"}


def test_bottom_mask_is_dropped_with_the_bottom_layer():
    """Disabling the bottom layer makes the next one the bottom: its mask is not built."""

    def no_clay(m):
        layer(m, "clay")["enabled"] = False

    material = cup_material(no_clay)
    assert material["layers"].startswith("glaze,") and "glaze_mask" not in material
    assert not [k for k in built_keys(material) if k.startswith("glaze.mask")]


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda m: layer(m, "lime").pop("mask"),
            "layer 'lime': needs a [material.layers.mask] table",
        ),
        (lambda m: layer(m, "lime")["mask"].update(scale=2.5), "material.lime.mask: scale = 2.5"),
        (lambda m: layer(m, "lime")["mask"].update(threshold=2.0), "threshold = 2.0 is outside"),
        (
            lambda m: layer(m, "lime")["mask"].update(texture="none.png"),
            "'none.png' is not a file",
        ),
        (lambda m: layer(m, "glaze").update(roughnes=0.1), "material.glaze.roughnes: unknown key"),
        (lambda m: layer(m, "glaze").update(type="plastic"), "material.glaze.type: got 'plastic'"),
        (lambda m: layer(m, "stain").update(name="lime"), "'lime' is used twice"),
        (  # refused whichever of the two is disabled (was: only when the second was)
            lambda m: (
                layer(m, "lime").update(enabled=False),
                layer(m, "stain").update(name="lime"),
            ),
            "'lime' is used twice",
        ),
        (  # the bottom layer's mask was ignored without a word, its missing texture too
            lambda m: layer(m, "clay").update(mask={"texture": "none.png", "threshold": 0.5}),
            "material.clay.mask: the bottom layer takes no mask",
        ),
        (  # the bottom by the layers below disabled: its mask is not built, but checked
            lambda m: (
                layer(m, "clay").update(enabled=False),
                layer(m, "glaze")["mask"].update(texture="none.png"),
            ),
            "'none.png' is not a file",
        ),
        (lambda m: m.update(bump=1.0), "bump = 1.0 is outside"),
        (lambda m: m.update(bumps=1.0), "[material]: has unknown key(s) bumps"),
    ],
)
def test_material_errors_name_the_key(edit, message):
    with pytest.raises(ConfigError) as err:
        cup_material(edit)
    assert message in str(err.value) and "cup.toml" in str(err.value)


def small(scene_table: dict, tmp_path) -> object:
    return parse_scene(scene_table, tmp_path / "s.toml")


CAMERA = {"origin": [0.0, -0.4, 0.12], "target": [0, 0, 0.05], "width": 24, "height": 24}


@pytest.mark.parametrize(
    "camera",
    [
        {**CAMERA, "fov_x_deg": 30},
        {**CAMERA, "fov_x_deg": 30, "aperture_radius": 0.003},
        {**CAMERA, "fov_x_deg": 30, "principal_point": [13.5, 11.0]},  # calibrated, off-centre
        {**CAMERA, "type": "orthographic", "ortho_width": 0.16},
    ],
)
@pytest.mark.parametrize(
    "light",
    [
        {
            "type": "rectangle",
            "center": [0.2, -0.3, 0.3],
            "target": [0, 0, 0],
            "size": [0.1, 0.1],
            "power": 2.0,
        },
        {"type": "point", "position": [0.2, -0.3, 0.3], "power": 2.0, "temperature": 4000},
        {"type": "directional", "direction": [-1, 1, -1], "irradiance": 2.0},
    ],
)
def test_every_camera_and_light_renders_the_cup(tmp_path, camera, light):
    scene = small({"geometry": "cup", "cameras": [camera], "lights": [light]}, tmp_path)
    image = render(load_scene(scene_dict(scene, {"type": "oren_nayar"}, 0, 8)), 8)
    cover = render(load_scene(coverage_dict(scene, 0, 8)), 8)[..., 0]
    assert np.all(np.isfinite(image))
    assert 0.1 < (cover > 0.5).mean() < 0.9  # the cup fills part of the frame
    assert image[cover > 0.99].mean() > 0.01  # and is lit


def test_point_light_power_is_radiometric(tmp_path):
    """A point light of power P above a Lambertian sphere: radiance at the pole is rho P/(4 pi d^2)
    / pi (within Monte Carlo noise)."""
    d, power, rho = 3.0, 100.0, 0.5
    scene = small(
        {
            "geometry": "sphere",
            "cameras": [
                {
                    "type": "orthographic",
                    "origin": [0, 0, 5],
                    "target": [0, 0, 0],
                    "up": [0, 1, 0],
                    "ortho_width": 0.05,
                    "width": 4,
                    "height": 4,
                }
            ],
            "lights": [{"type": "point", "position": [0, 0, 1 + d], "power": power}],
        },
        tmp_path,
    )
    image = render(
        mi.load_dict(
            scene_dict(
                scene,
                {"type": "oren_nayar", "reflectance": {"type": "rgb", "value": [rho] * 3}},
                0,
                16,
            )
        ),
        16,
    )
    expected = rho / math.pi * power / (4 * math.pi * d**2)
    assert image.mean() == pytest.approx(expected, rel=0.02)


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
@pytest.mark.parametrize("scale", [1e-3, 1e3, "target 1e4x farther", "target 1e7x nearer"])
def test_a_scene_of_any_scale_renders_its_object(kind, scale):
    """The glazed sphere and its cameras scaled down (the camera 4 mm from a 1 mm sphere: the
    default near clip, 0.01 m, rendered only the background) or up (kilometres, within the
    far clip); its target far beyond the sphere or right before the camera (the clip range
    follows the object, not only the target)."""
    import dataclasses

    from captures.scene import Sphere

    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    origin = np.asarray(cfg.scene.cameras[0].origin)
    target = np.asarray(cfg.scene.cameras[0].target)
    if isinstance(scale, str):  # the same view, its target moved along it (5.1 m away):
        # 51 km beyond put the near clip (a thousandth of the target's distance) past the
        # sphere; 0.5 um before the camera, the far clip (1e4) stays beyond it either way
        factor = 1e4 if "farther" in scale else 1e-7
        target, scale = origin + factor * (target - origin), 1.0
    camera = dataclasses.replace(
        cfg.scene.cameras[0],
        width=16,
        height=12,
        origin=tuple(float(scale * c) for c in origin),
        target=tuple(float(scale * c) for c in target),
        kind=kind,
        ortho_width=3.0 * scale,
    )
    scene = dataclasses.replace(
        cfg.scene, cameras=(camera,), geometry=Sphere(radius=scale), lights=()
    )
    image = render(load_scene(scene_dict(scene, cfg.material, 0, 4)), 4, 0)
    background = np.asarray(cfg.scene.environment, np.float32)
    # the sphere (a dimmer glaze over the grey environment) covers the centre
    assert not np.allclose(image[6, 8], background, rtol=0.02)


def test_an_environment_maps_sky_is_up(tmp_path):
    """An equirectangular map's top row (its sky) lights from +z, world up; its centre column
    from -y (Mitsuba's own envmap has its top towards +y)."""
    import dataclasses

    import drjit as dr

    from captures.images import write_image
    from captures.scene import EnvMap
    from fit.render.scene import environment_dict

    image = np.zeros((64, 128, 3), np.float32)
    image[:4] = 5.0  # the top rows
    image[28:36, 60:68] = 1.0  # the centre
    write_image(tmp_path / "sky.exr", image)
    sphere = load_render_config(ROOT / "configs" / "glazed-sphere.toml").scene
    scene = dataclasses.replace(sphere, environment=EnvMap(tmp_path / "sky.exr"))
    emitter = mi.load_dict(environment_dict(scene))

    def arriving_from(direction) -> float:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*(-float(c) for c in direction))
        return float(emitter.eval(si)[0][0])

    assert arriving_from([0, 0, 1]) == pytest.approx(5.0, rel=0.05)
    assert arriving_from([0, -1, 0]) == pytest.approx(1.0, rel=0.05)
    assert arriving_from([0, 1, 0]) == arriving_from([0, 0, -1]) == 0.0


def test_a_scene_loads_its_lights_in_order_so_a_seed_repeats(tmp_path):
    """Mitsuba's default load merges meshes that share a material and then lists the shapes in
    an order that varies between loads (two identical lights swapped in 7 of 100 loads): the
    emitter a random number picks follows it, so a seed's render changed. `load_scene` keeps
    the dict's order; 40 loads of a scene with two identical lights render alike."""
    from fit.render import load_scene

    light = {"type": "rectangle", "target": [0, 0, 0], "size": [0.5, 0.5], "radiance": 50.0}
    scene = small(
        {
            "geometry": "sphere",
            "cameras": [
                {
                    "origin": [0, -4, 1],
                    "target": [0, 0, 0],
                    "fov_x_deg": 30,
                    "width": 8,
                    "height": 6,
                }
            ],
            "lights": [{**light, "center": [2, -2, 2]}, {**light, "center": [-2, -2, 2]}],
        },
        tmp_path,
    )
    d = scene_dict(scene, {"type": "diffuse"}, 0, 4)
    orders = {tuple(s.id() for s in load_scene(d).shapes()) for _ in range(40)}
    assert orders == {("object", "light_0", "light_1")}
    first = render(load_scene(d), 4, 3)
    assert all(np.array_equal(render(load_scene(d), 4, 3), first) for _ in range(5))


def test_face_normals_render_a_shared_vertex_box_as_its_faces(tmp_path):
    """A cube of 8 shared vertices without normals renders rounded (Mitsuba interpolates
    normals); with `face_normals = true` it renders as the same cube with its faces apart."""
    from fit.render import load_scene

    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    shared = [f"v {x} {y} {z}" for x, y, z in corners] + [
        f"f {a} {b} {c} {d}" for a, b, c, d in quads
    ]
    (tmp_path / "shared.obj").write_text("\n".join(shared) + "\n")
    apart = [f"v {x} {y} {z}" for q in quads for x, y, z in (corners[i - 1] for i in q)]
    apart += [f"f {4 * k + 1} {4 * k + 2} {4 * k + 3} {4 * k + 4}" for k in range(6)]
    (tmp_path / "apart.obj").write_text("\n".join(apart) + "\n")
    camera = {"origin": [4, -5, 3], "target": [0, 0, 0], "fov_x_deg": 40, "width": 24, "height": 18}
    light = {"type": "directional", "direction": [-1, 2, -3], "irradiance": 3.0}

    def image(geometry):
        scene = small({"geometry": geometry, "cameras": [camera], "lights": [light]}, tmp_path)
        return render(load_scene(scene_dict(scene, {"type": "diffuse"}, 0, 16)), 16, 1)

    reference = image("apart.obj")
    rounded = np.abs(image("shared.obj") - reference).mean()
    flat = np.abs(image({"type": "obj", "file": "shared.obj", "face_normals": True}) - reference)
    assert rounded > 0.05 * reference.mean()
    assert flat.mean() < 0.01 * rounded


def open_cylinder(path: Path, inward: bool = False, segments: int = 48, normals=False) -> Path:
    """A tube of radius 1 and height 2 standing on z = 0, without caps (wound outward unless
    `inward`; with `normals`, radial `vn` normals)."""
    n, lines = segments, []
    for i in range(n):
        a = 2 * np.pi * i / n
        lines += [f"v {np.cos(a)} {np.sin(a)} 0", f"v {np.cos(a)} {np.sin(a)} 2"]
        lines += [f"vn {np.cos(a)} {np.sin(a)} 0"] * 2 if normals else []
    for i in range(n):
        a, b = 2 * i + 1, 2 * ((i + 1) % n) + 1
        for face in [(a, b, b + 1), (a, b + 1, a + 1)]:
            wound = face[::-1] if inward else face
            lines.append("f " + " ".join(f"{k}//{k}" if normals else str(k) for k in wound))
    path.write_text("\n".join(lines) + "\n")
    return path


def closed_cube(path: Path, wound_inward: bool, normals: int) -> Path:
    """The cube [-1, 1]^3 moved up by 1, its faces wound inward or outward, with per-face `vn`
    normals pointing out (`normals` 1) or in (-1)."""
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)]
    lines = [f"v {x} {y} {z + 1}" for x, y, z in corners]
    for k, quad in enumerate(quads, 1):
        centre = np.mean([corners[i - 1] for i in quad], axis=0)
        lines.append("vn " + " ".join(str(int(normals * c)) for c in np.sign(centre)))
        p = np.array([corners[i - 1] for i in quad], float)
        outward = np.cross(p[1] - p[0], p[2] - p[0]) @ centre > 0
        wound = quad if outward != wound_inward else quad[::-1]
        lines.append("f " + " ".join(f"{i}//{k}" for i in wound))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    "lens",
    [
        {},
        {"aperture_radius": 0.05},  # a thin lens: the pixel centres' rays through its centre
        {"type": "orthographic", "ortho_width": 4.0},
    ],
)
@pytest.mark.parametrize(
    "geometry, origin, seen_from_behind",
    [
        ("sphere", [0, -4, 1], False),
        ("cup", [0, -0.5, 0.4], False),  # looking into the cup: its inside has thickness
        ("tube.obj", [0, -5, 1], False),  # from the side: its outside only
        ("tube.obj", [0, -3, 5], True),  # from above: its inside, the backs of its faces
        ("inward.obj", [0, -5, 1], True),  # wound inside out, no normals: they point inward
        ("cube.obj", [0, -5, 1], False),  # wound inside out, normals given outward: lit
        ("inward-normals.obj", [0, -5, 1], True),  # wound outward, normals given inward: black
        ("coarse.obj", [0, -5, 1], False),  # 8 segments: normals dip at the silhouette
    ],
)
def test_faces_seen_from_behind_are_warned(tmp_path, geometry, origin, seen_from_behind, lens):
    """The materials are one-sided, by the shading normal: a view that sees the surface from
    behind (an open mesh from its inside, normals pointing inward) renders it black; the fit
    warns, naming the views. A mesh wound inside out whose `vn` normals point out renders lit,
    and is not warned."""
    from fit.render.scene import view_warnings

    open_cylinder(tmp_path / "tube.obj")
    open_cylinder(tmp_path / "inward.obj", inward=True)
    open_cylinder(tmp_path / "coarse.obj", segments=8, normals=True)
    closed_cube(tmp_path / "cube.obj", wound_inward=True, normals=1)
    closed_cube(tmp_path / "inward-normals.obj", wound_inward=False, normals=-1)
    target = [0, 0, 0.05] if geometry == "cup" else [0, 0, 1]
    camera = {"origin": origin, "target": target, "fov_x_deg": 40, "width": 63, "height": 47}
    if lens.get("type") == "orthographic":
        del camera["fov_x_deg"]
        if geometry == "cup":
            lens = {**lens, "ortho_width": 0.2}
    camera.update(lens)
    light = {"center": [2, -2, 4], "target": [0, 0, 0], "size": [0.5, 0.2], "power": 10.0}
    scene = parse_scene(
        {"geometry": geometry, "cameras": [camera], "lights": [light]}, tmp_path / "s.toml"
    )
    views = [("v0", scene.cameras[0]), ("v1", scene.cameras[0])]  # sharing a camera
    said = view_warnings(scene, views, "cap")
    assert len(said) == seen_from_behind, said
    warning = said[0] if said else None
    if seen_from_behind:
        assert warning.startswith("cap: 2 of 2 views see the object's faces from behind")
        assert "in v0, v1;" in warning


def test_views_that_show_no_object_are_warned(tmp_path):
    """A view whose object is under a pixel (cameras in millimetres around a 1 m sphere: 500 m
    away) shows it at no traced pixel centre: the fit warns, naming the view (it fitted the
    view's background without a word, every parameter then undetermined)."""
    from fit.render.scene import view_warnings

    near = {"origin": [0, -5, 1], "target": [0, 0, 0], "fov_x_deg": 40, "width": 32, "height": 24}
    far = {**near, "origin": [0, -500, 100]}
    light = {"center": [2, -2, 4], "target": [0, 0, 0], "size": [0.5, 0.2], "power": 10.0}
    scene = parse_scene(
        {"geometry": "sphere", "cameras": [near, far], "lights": [light]}, tmp_path / "s.toml"
    )
    views = [("near", scene.cameras[0]), ("far", scene.cameras[1])]
    (warning,) = view_warnings(scene, views, "cap")
    assert warning.startswith("cap: 1 of 2 views show the object at none of their traced pixel")
    assert "(in far)" in warning and "units" in warning
    assert view_warnings(scene, views[:1], "cap") == []


def test_a_silhouette_off_its_object_mask_is_warned(tmp_path):
    """A view whose object mask the traced silhouette barely overlaps (a Y-up mesh in a Z-up
    scene scored IoU 0.37-0.69 on the Cycles torus, a misplaced camera) is warned, naming the
    view and its IoU; the fit ran without a word. Aligned, nothing is said (the shared peers'
    views score 0.94-0.99)."""
    from fit.render.scene import trace_silhouettes, view_warnings

    camera = {"origin": [0, -5, 1], "target": [0, 0, 0], "fov_x_deg": 40, "width": 40, "height": 30}
    moved = {**camera, "origin": [1.2, -5, 1], "target": [1.2, 0, 0]}  # the photo's pose
    light = {"center": [2, -2, 4], "target": [0, 0, 0], "size": [0.5, 0.2], "power": 10.0}
    scene = parse_scene(
        {"geometry": "sphere", "cameras": [camera, moved], "lights": [light]}, tmp_path / "s.toml"
    )
    (hit, _), (photo, _) = trace_silhouettes(scene, list(scene.cameras))
    views = [("aligned", scene.cameras[0]), ("off", scene.cameras[0])]
    (warning,) = view_warnings(scene, views, "cap", [(hit, 0.5), (photo, 0.5)])
    assert warning.startswith("cap: the object's silhouette overlaps the object mask of 1 of 2")
    assert "IoU off 0." in warning and "aligned" not in warning and "axes" in warning
    assert view_warnings(scene, views, "cap", [(hit, 0.5), None]) == []


def test_a_crack_between_triangles_on_pixel_centres_is_not_a_back_face(tmp_path):
    """A closed cylinder (radius 0.1, length 2, caps, radial `vn`) seen by orthographic cameras
    0.8 wide at 72 pixels: an edge of its side projects onto a column of pixel centres, and some
    of those rays slipped through the crack between its triangles onto the far wall's inside.
    11 of 1728 cells were taken as seen from behind and two views warned; its renders hold no
    black pixel."""
    from fit.render.scene import view_warnings

    n, r, lines = 48, 0.1, []
    for i in range(n):
        a = 2 * np.pi * i / n
        lines += [f"v {r * np.cos(a)} {r * np.sin(a)} {z}" for z in (-1, 1)]
        lines += [f"vn {np.cos(a)} {np.sin(a)} 0"]
    lines += ["v 0 0 -1", "v 0 0 1", "vn 0 0 -1", "vn 0 0 1"]
    bottom, top = 2 * n + 1, 2 * n + 2
    for i in range(n):
        j = (i + 1) % n
        a, b, c, d = 2 * i + 1, 2 * j + 1, 2 * j + 2, 2 * i + 2
        lines += [f"f {a}//{i + 1} {b}//{j + 1} {c}//{j + 1}"]
        lines += [f"f {a}//{i + 1} {c}//{j + 1} {d}//{i + 1}"]
        lines += [f"f {bottom}//{n + 1} {b}//{n + 1} {a}//{n + 1}"]
        lines += [f"f {top}//{n + 2} {d}//{n + 2} {c}//{n + 2}"]
    (tmp_path / "cyl.obj").write_text("\n".join(lines) + "\n")
    cameras = [
        {"type": "orthographic", "origin": o, "target": [0, 0, 0], "ortho_width": 0.8}
        | {"width": 72, "height": 96}
        for o in ([0, -5, 1.2], [3.5, -3.5, 0.8], [-2.5, -4, 2.5])
    ]
    light = {"center": [3, -2.5, 3], "target": [0, 0, 0], "size": [1.2, 0.8], "power": 10.0}
    scene = parse_scene(
        {"geometry": {"type": "obj", "file": "cyl.obj"}, "cameras": cameras, "lights": [light]},
        tmp_path / "s.toml",
    )
    views = [(f"v{k}", camera) for k, camera in enumerate(scene.cameras)]
    assert view_warnings(scene, views, "cap") == []
