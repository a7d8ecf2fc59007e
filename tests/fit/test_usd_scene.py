"""`layerfit export --to usd --with-scene`: the object's stage read back with pxr, for each kind of
capture (the analytic sphere with every camera and light kind, the procedural cup with thin
lenses, a peer's OBJ, a photometric-stereo height field); its cameras traced against layerfit's
own sensors; what it refuses."""

from __future__ import annotations

import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from typer.testing import CliRunner

from captures import open_capture
from captures.capture import manifest_text
from captures.geometry import cup_mesh
from captures.images import write_image
from fit.cli import app
from fit.commands.export import export
from fit.export.usd_scene import APERTURE, POINT_RADIUS, SPHERE_SEGMENTS, look_at, sphere_mesh
from fit.material import build_material, save_preset
from fit.render.scene import sensor_dict

ROOT = Path(__file__).resolve().parents[2]
CUP = ROOT / "captures" / "samples" / "cup"
GLAZE = {"type": "glaze", "pigment": [0.55, 0.33, 0.12], "roughness": 0.02, "ior": 1.5}
SPHERE = {"type": "sphere", "center": [0.1, 0.2, 0.3], "radius": 0.5}
#: A pinhole with a calibrated principal point, a thin lens, an orthographic camera.
CAMERAS = [
    {
        "origin": [0.3, -3.0, 1.2],
        "target": [0.1, 0.2, 0.3],
        "fov_x_deg": 30.0,
        "principal_point": [35.0, 22.0],
        "width": 64,
        "height": 48,
    },
    {
        "origin": [-2.5, -1.5, 1.0],
        "target": [0.1, 0.2, 0.3],
        "fov_x_deg": 35.0,
        "aperture_radius": 0.02,
        "focus_distance": 2.8,
        "width": 64,
        "height": 48,
    },
    {
        "type": "orthographic",
        "origin": [2.5, 1.0, 1.8],
        "target": [0.1, 0.2, 0.3],
        "ortho_width": 1.6,
        "width": 48,
        "height": 40,
    },
]
LIGHTS = [
    {
        "type": "rectangle",
        "center": [1.5, -1.5, 2.0],
        "target": [0.1, 0.2, 0.3],
        "size": [0.6, 0.4],
        "radiance": [30.0, 25.0, 20.0],
    },
    {"type": "point", "position": [-1.5, -2.0, 1.5], "intensity": [2.0, 2.5, 3.0]},
    {"type": "directional", "direction": [-0.3, 0.5, -1.0], "irradiance": [0.8, 0.7, 0.6]},
]


def make_capture(folder: Path, geometry=None, cameras=None, lights=None, environment=None) -> Path:
    """A capture manifest in `folder` (its photos flat grey: only its scene matters here)."""
    folder.mkdir(parents=True, exist_ok=True)
    views = []
    for i, camera in enumerate(cameras or CAMERAS):
        write_image(folder / f"v{i}.exr", np.full((camera["height"], camera["width"], 3), 0.2))
        views.append({"image": f"v{i}.exr", "camera": camera})
    scene = {
        "geometry": geometry or SPHERE,
        "environment": environment or [0.05, 0.06, 0.07],
        "lights": LIGHTS if lights is None else lights,
    }
    text = manifest_text({"encoding": "linear"}, scene, views, {})
    (folder / "capture.toml").write_text(text)
    return folder


def preset(folder: Path, table=None, capture: Path | None = None) -> Path:
    """A preset of `table` (the glaze), its provenance naming `capture` where given."""
    material = build_material(table or GLAZE, folder / "m.toml")
    provenance = {"capture": str(capture)} if capture is not None else None
    return save_preset(material, folder / "m.toml", provenance)


def stage_of(path: Path):
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    assert stage is not None
    return stage


def lights_of(stage) -> dict[str, object]:
    from pxr import Usd, UsdLux

    return {
        prim.GetName(): prim
        for prim in Usd.PrimRange(stage.GetPrimAtPath("/Scene/Lights"))
        if prim.HasAPI(UsdLux.LightAPI)
    }


def radiance(prim) -> np.ndarray:
    """A light's `intensity` x `color`."""
    from pxr import UsdLux

    light = UsdLux.LightAPI(prim)
    return light.GetIntensityAttr().Get() * np.array(light.GetColorAttr().Get())


def check_object(stage, surface_points: int | None = None) -> np.ndarray:
    """The common checks: units, axis, a mesh with `st` per vertex and normals, the exported
    material bound; the mesh's points."""
    from pxr import UsdGeom, UsdShade

    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Object"))
    assert mesh and mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    points = np.array(mesh.GetPointsAttr().Get())
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    assert np.all(counts == 3) and len(indices) == 3 * len(counts) and indices.max() < len(points)
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex
    assert np.array(st.Get()).shape == (len(points), 2)
    assert np.array(mesh.GetNormalsAttr().Get()).shape[0] in (len(points), len(indices))
    if surface_points is not None:
        assert len(points) == surface_points
    material, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
    assert material.GetPath() == "/Scene/Looks/Material"
    shader = material.ComputeSurfaceSource()[0]
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    return points


def cameras_of(stage) -> dict[str, object]:
    from pxr import Usd, UsdGeom

    return {
        prim.GetName(): UsdGeom.Camera(prim)
        for prim in Usd.PrimRange(stage.GetPrimAtPath("/Scene/Cameras"))
        if prim.IsA(UsdGeom.Camera)
    }


def test_sphere_stage_holds_every_camera_and_light_kind(tmp_path):
    """The analytic sphere as a UV sphere on it with Mitsuba's UVs (v flipped, as the maps are
    laid out), three cameras with their resolutions, each light kind with its radiance."""
    from pxr import Gf, UsdLux, UsdRender

    capture = make_capture(tmp_path / "capture")
    path = export(
        preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=capture
    )
    assert path == tmp_path / "out" / "scene.usda"
    stage = stage_of(path)
    n = (SPHERE_SEGMENTS + 1) * (SPHERE_SEGMENTS // 2 + 1)
    points = check_object(stage, n)
    np.testing.assert_allclose(np.linalg.norm(points - SPHERE["center"], axis=1), 0.5, rtol=1e-6)
    # the UVs are Mitsuba's where a ray meets the sphere, v flipped
    from pxr import UsdGeom

    st = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Scene/Object")).GetPrimvar("st").Get())
    sphere = mi.load_dict({"type": "scene", "s": {"type": "sphere", **SPHERE}})
    pick = np.random.default_rng(0).choice(
        np.flatnonzero((st[:, 1] > 0.01) & (st[:, 1] < 0.99) & (st[:, 0] < 0.99)), 50
    )
    outward = (points[pick] - SPHERE["center"]) / 0.5
    origins = points[pick] + outward
    hit = sphere.ray_intersect(mi.Ray3f(mi.Point3f(*origins.T), mi.Vector3f(*(-outward).T)))
    uv = np.array(hit.uv).T.reshape(-1, 2)
    np.testing.assert_allclose(st[pick], np.stack([uv[:, 0], 1 - uv[:, 1]], -1), atol=1e-4)

    cameras = cameras_of(stage)
    assert sorted(cameras) == ["v0", "v1", "v2"]
    for name, camera in zip(["v0", "v1", "v2"], CAMERAS, strict=True):
        settings = UsdRender.Settings(stage.GetPrimAtPath(f"/Render/{name}"))
        assert tuple(settings.GetResolutionAttr().Get()) == (camera["width"], camera["height"])
        assert settings.GetCameraRel().GetTargets() == [cameras[name].GetPath()]
    assert stage.GetMetadata("renderSettingsPrimPath") == "/Render/v0"
    thin = cameras["v1"]
    focal = thin.GetFocalLengthAttr().Get() * Gf.Camera.FOCAL_LENGTH_UNIT
    assert focal / (2 * thin.GetFStopAttr().Get()) == pytest.approx(0.02, rel=1e-6)
    assert thin.GetFocusDistanceAttr().Get() == pytest.approx(2.8)
    assert not cameras["v0"].GetFStopAttr().HasAuthoredValue()  # a pinhole: no depth of field

    lights = lights_of(stage)
    assert sorted(lights) == ["Environment", "Light_0", "Light_1", "Light_2"]
    rect, point, sun, dome = (lights[k] for k in ("Light_0", "Light_1", "Light_2", "Environment"))
    assert rect.IsA(UsdLux.RectLight) and point.IsA(UsdLux.SphereLight)
    assert sun.IsA(UsdLux.DistantLight) and dome.IsA(UsdLux.DomeLight)
    np.testing.assert_allclose(radiance(rect), LIGHTS[0]["radiance"], rtol=1e-6)
    rect_light = UsdLux.RectLight(rect)
    assert (rect_light.GetWidthAttr().Get(), rect_light.GetHeightAttr().Get()) == pytest.approx(
        (0.6, 0.4)
    )
    # it emits along its local -z: towards the target
    to_world = np.array(UsdGeom.Xformable(rect).ComputeLocalToWorldTransform(0))
    facing = np.array(SPHERE["center"]) - LIGHTS[0]["center"]
    np.testing.assert_allclose(-to_world[2, :3], facing / np.linalg.norm(facing), atol=1e-6)
    # the point light: a small sphere whose radiance x its disc is the intensity
    r = UsdLux.SphereLight(point).GetRadiusAttr().Get()
    distance = np.linalg.norm(np.subtract(LIGHTS[1]["position"], SPHERE["center"]))
    assert r == pytest.approx(POINT_RADIUS * distance, rel=1e-6)
    np.testing.assert_allclose(radiance(point) * math.pi * r**2, LIGHTS[1]["intensity"], 1e-5)
    assert not UsdLux.SphereLight(point).GetTreatAsPointAttr().Get()
    # the distant light: the irradiance, travelling along its local -z
    assert UsdLux.LightAPI(sun).GetNormalizeAttr().Get()
    assert UsdLux.DistantLight(sun).GetAngleAttr().Get() == 0
    np.testing.assert_allclose(radiance(sun), LIGHTS[2]["irradiance"], rtol=1e-6)
    to_world = np.array(UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(0))
    travel = np.array(LIGHTS[2]["direction"]) / np.linalg.norm(LIGHTS[2]["direction"])
    np.testing.assert_allclose(-to_world[2, :3], travel, atol=1e-6)
    np.testing.assert_allclose(radiance(dome), [0.05, 0.06, 0.07], rtol=1e-6)


def rays(sensor, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's rays (origins, directions) through film positions `xy` (0 to 1 from the
    top-left), through the lens's centre."""
    x, y = mi.Float(xy[:, 0]), mi.Float(xy[:, 1])
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))

    def points(v) -> np.ndarray:  # a pinhole's origin is one point for every ray
        return np.stack([np.broadcast_to(np.array(c), len(xy)) for c in (v.x, v.y, v.z)], -1)

    return points(ray.o), points(ray.d)


def test_cameras_trace_the_rays_layerfit_renders(tmp_path):
    """Through every camera (a principal point, a thin lens's centre, orthographic) the USD
    camera's frustum casts the rays Mitsuba's sensor casts through the same film positions."""
    from pxr import Gf

    capture = make_capture(tmp_path / "capture")
    path = export(
        preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=capture
    )
    stage = stage_of(path)  # held: its prims are valid while it lives
    cameras = cameras_of(stage)
    xy = np.array([[0.5, 0.5], [0.05, 0.1], [0.9, 0.2], [0.3, 0.95], [0.97, 0.97]])
    for name, camera in zip(["v0", "v1", "v2"], open_capture(capture).scene.cameras, strict=True):
        sensor = mi.load_dict(sensor_dict(camera, 1))
        origins, directions = rays(sensor, xy)
        frustum = cameras[name].GetCamera(0).frustum
        for (x, y), o, d in zip(xy, origins, directions, strict=True):
            ray = frustum.ComputePickRay(Gf.Vec2d(2 * x - 1, 1 - 2 * y))
            start, along = np.array(ray.startPoint), np.array(ray.direction)
            along /= np.linalg.norm(along)
            np.testing.assert_allclose(along, d, atol=1e-5, err_msg=name)
            # the same line: Mitsuba's origin on the USD ray's
            off = (o - start) - np.dot(o - start, along) * along
            assert np.linalg.norm(off) < 1e-5, name


def test_cup_capture_holds_its_mesh_and_thin_lenses(tmp_path):
    """The bundled cup: its procedural mesh (Mitsuba's UVs, v flipped), five thin-lens cameras,
    two rectangles and the constant environment."""
    from pxr import UsdGeom, UsdLux

    path = export(preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=CUP)
    stage = stage_of(path)
    cup = cup_mesh(open_capture(CUP).scene.geometry.shape)
    points = check_object(stage, len(cup.positions))
    np.testing.assert_allclose(points, cup.positions, atol=1e-7)
    st = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Scene/Object")).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, np.stack([cup.uvs[:, 0], 1 - cup.uvs[:, 1]], -1), atol=1e-6)
    cameras = cameras_of(stage)
    assert len(cameras) == 5
    assert all(c.GetFStopAttr().Get() > 0 for c in cameras.values())
    lights = lights_of(stage)
    assert sum(p.IsA(UsdLux.RectLight) for p in lights.values()) == 2
    np.testing.assert_allclose(radiance(lights["Environment"]), [0.05, 0.055, 0.065], rtol=1e-6)


def test_peer_mesh_scene(tmp_path, shared_data):
    """A peer's scene.json: its OBJ as Mitsuba loads it (UVs as the file stores them), five
    cameras at the views' resolution, its rectangles and world."""
    from pxr import UsdGeom, UsdLux, UsdRender

    scene_json = shared_data / "peer-cycles" / "torus-amber" / "scene.json"
    # the capture from the preset's provenance, as a fit's preset names it
    path = export(
        preset(tmp_path, capture=scene_json), "usd", tmp_path / "out", size=8, with_scene=True
    )
    stage = stage_of(path)
    loaded = mi.load_dict({"type": "obj", "filename": str(scene_json.parent / "mesh.obj")})
    params = mi.traverse(loaded)
    points = check_object(stage, loaded.vertex_count())
    np.testing.assert_allclose(
        points, np.array(params["vertex_positions"]).reshape(-1, 3), atol=1e-6
    )
    uv = np.array(params["vertex_texcoords"]).reshape(-1, 2)
    st = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Scene/Object")).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, np.stack([uv[:, 0], 1 - uv[:, 1]], -1), atol=1e-6)
    # the file's own first texture coordinates (vt 0.5 0.5, 0.507812 0.5, 0.507812 0.520833)
    np.testing.assert_allclose(st[2], [0.507812, 0.520833], atol=1e-6)
    cameras = cameras_of(stage)
    assert sorted(cameras) == [f"view_0{i}" for i in range(5)]
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/view_00"))
    assert tuple(settings.GetResolutionAttr().Get()) == (160, 120)
    lights = lights_of(stage)
    rects = [lights[f"Light_{i}"] for i in range(2)]
    assert all(p.IsA(UsdLux.RectLight) for p in rects)
    capture = open_capture(scene_json)
    for prim, light in zip(rects, capture.scene.lights, strict=True):
        np.testing.assert_allclose(radiance(prim), light.radiance, rtol=1e-6)
    np.testing.assert_allclose(radiance(lights["Environment"]), [0.06, 0.06, 0.07], rtol=1e-6)


def test_height_field_scene(tmp_path, shared_data):
    """A DiLiGenT object that is no ball: its normal map's height field with UVs of its image
    coordinates, the one orthographic camera its views share, each view's distant light in a
    variant of `/Scene/Lights`."""
    from pxr import UsdGeom, UsdLux

    folder = shared_data / "diligent-pot1"
    path = export(
        preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=folder
    )
    stage = stage_of(path)
    capture = open_capture(folder)
    data = capture.scene.geometry.data
    points = check_object(stage, len(data.positions))
    np.testing.assert_allclose(points, data.positions, rtol=1e-6)
    st = np.array(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Scene/Object")).GetPrimvar("st").Get())
    h, w = capture.scene.meta["mask"].shape  # x right, y up from the bottom-left, over W and H
    pixel = np.stack([data.positions[:, 0] + w / 2, h / 2 + data.positions[:, 1]], -1)
    np.testing.assert_allclose(st, pixel / [w, h], atol=1e-6)
    (camera,) = cameras_of(stage).values()
    assert camera.GetProjectionAttr().Get() == UsdGeom.Tokens.orthographic
    assert list(camera.GetPrim().GetCustomDataByKey("layerfit:views")) == [
        v.name for v in capture.views
    ]
    lights_prim = stage.GetPrimAtPath("/Scene/Lights")
    variants = lights_prim.GetVariantSets().GetVariantSet("view")
    names = variants.GetVariantNames()
    assert len(names) == len(capture.views) == 16
    for name, view in zip(names, capture.views, strict=True):
        variants.SetVariantSelection(name)
        (sun,) = lights_of(stage).values()
        assert sun.IsA(UsdLux.DistantLight)
        to_world = np.array(UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(0))
        np.testing.assert_allclose(-to_world[2, :3], view.lights[0].direction, atol=1e-6)


def test_an_environment_map_is_a_turned_dome(tmp_path):
    """An environment map is copied beside the stage as a lat-long dome, scaled, turned so its
    top row is +z and its centre column faces -y (as layerfit turns Mitsuba's envmap)."""
    from pxr import UsdGeom, UsdLux

    sky = np.linspace(0.1, 1.0, 8 * 16 * 3).reshape(8, 16, 3).astype(np.float32)
    (tmp_path / "capture").mkdir()
    write_image(tmp_path / "capture" / "sky.exr", sky)
    env = {"type": "envmap", "file": "sky.exr", "scale": 2.5}
    capture = make_capture(tmp_path / "capture", environment=env, lights=[])
    path = export(
        preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=capture
    )
    stage = stage_of(path)
    dome = UsdLux.DomeLight(stage.GetPrimAtPath("/Scene/Lights/Environment"))
    assert dome.GetTextureFileAttr().Get().path == "./environment.exr"
    assert dome.GetTextureFormatAttr().Get() == UsdLux.Tokens.latlong
    assert dome.GetIntensityAttr().Get() == pytest.approx(2.5)
    assert (tmp_path / "out" / "environment.exr").read_bytes() == (
        tmp_path / "capture" / "sky.exr"
    ).read_bytes()
    m = np.array(UsdGeom.Xformable(dome.GetPrim()).ComputeLocalToWorldTransform(0))
    np.testing.assert_allclose(m[1, :3], [0, 0, 1], atol=1e-12)  # the top row: up
    np.testing.assert_allclose(m[2, :3], [0, -1, 0], atol=1e-12)  # the centre column


def test_a_flat_shaded_obj_and_one_without_uvs(tmp_path):
    """`face_normals`: each face's own normal at its corners; an OBJ without UVs holds no `st`,
    and a material with maps on it is refused in one line (nothing written)."""
    from pxr import UsdGeom

    obj = tmp_path / "capture" / "pyramid.obj"
    obj.parent.mkdir()
    corners = "v -0.5 -0.5 0\nv 0.5 -0.5 0\nv 0.5 0.5 0\nv -0.5 0.5 0\nv 0 0 0.6\n"
    faces = "f 1 4 3\nf 1 3 2\nf 1 2 5\nf 2 3 5\nf 3 4 5\nf 4 1 5\n"
    obj.write_text(corners + faces)
    cameras = [dict(CAMERAS[0], target=[0, 0, 0.2])]
    geometry = {"type": "obj", "file": "pyramid.obj", "face_normals": True}
    capture = make_capture(obj.parent, geometry=geometry, cameras=cameras, lights=LIGHTS[:1])
    path = export(
        preset(tmp_path), "usd", tmp_path / "out", size=8, with_scene=True, capture=capture
    )
    stage = stage_of(path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Object"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.faceVarying
    normals = np.array(mesh.GetNormalsAttr().Get()).reshape(-1, 3, 3)
    assert np.allclose(normals[0], [0, 0, -1]) and np.allclose(normals[:, 0], normals[:, 2])
    assert not UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    textured = {"type": "glaze", "pigment_noise": 0.3}
    with pytest.raises(ValueError, match=r"pyramid.obj: the OBJ has no texture coordinates"):
        export(
            preset(tmp_path, textured),
            "usd",
            tmp_path / "maps",
            size=8,
            with_scene=True,
            capture=capture,
        )
    assert not (tmp_path / "maps").exists()


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_line(result) -> str:
    (line,) = [x for x in result.output.splitlines() if x.strip()]
    return line


def test_cli_with_scene_from_a_run_folder_and_force(tmp_path):
    """A run folder's preset names its capture; `--force` replaces an earlier scene export (its
    mesh and maps its own) but never a file of the user's beside it."""
    run = tmp_path / "run3"
    run.mkdir()
    capture = make_capture(tmp_path / "capture")
    save_preset(
        build_material(GLAZE, run / "preset.toml"), run / "preset.toml", {"capture": str(capture)}
    )
    out = tmp_path / "usd"
    first = cli("export", run, "--to", "usd", "--with-scene", "--out", out, "--size", 8)
    assert first.exit_code == 0, first.output
    assert "scene.usda" in first.output
    assert sorted(p.name for p in out.iterdir()) == [
        ".layerfit-export",
        "material.usda",
        "object.usdc",
        "scene.usda",
    ]
    again = cli("export", run, "--to", "usd", "--with-scene", "--out", out, "--force")
    assert again.exit_code == 0, again.output
    (out / "notes.txt").write_text("mine")
    kept = cli("export", run, "--to", "usd", "--with-scene", "--out", out, "--force")
    assert kept.exit_code == 2 and "also holds notes.txt" in one_line(kept)
    assert (out / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize(
    "case, message",
    [
        ("no capture", "names no capture (provenance.capture"),
        ("gone", "does not exist (moved or deleted?); give the capture with --capture"),
        ("mitsuba", "--with-scene: applies to --to usd only (got --to mitsuba)"),
        ("capture alone", "--capture: names the scene's capture; add --with-scene"),
        ("empty run", "a folder without preset.toml"),
    ],
)
def test_cli_with_scene_bad_input_is_one_line(tmp_path, case, message):
    file = preset(tmp_path, capture=tmp_path / "gone" if case == "gone" else None)
    args = ["--to", "usd", "--with-scene"]
    if case == "mitsuba":
        args = ["--to", "mitsuba", "--with-scene"]
    elif case == "capture alone":
        args = ["--to", "usd", "--capture", tmp_path]
    elif case == "empty run":
        file = tmp_path / "run"
        file.mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    result = cli("export", file, *args, "--out", tmp_path / "out")
    assert result.exit_code == 2, result.output
    assert message in one_line(result)
    if case == "no capture":
        assert "--capture" in one_line(result)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_camera_frame_is_mitsubas_look_at():
    """The camera's frame is Mitsuba's `look_at` with x and z negated (x right in the image, the
    view along -z), and the aperture reads as a 36 mm sensor."""
    from captures.scene import Camera

    camera = Camera((1.0, -2.0, 0.5), (0.0, 0.3, 0.1), (0.0, 0.0, 1.0), 40.0, 64, 48)
    m = np.array(mi.ScalarTransform4f().look_at(camera.origin, camera.target, camera.up).matrix)
    usd = look_at(camera)
    np.testing.assert_allclose(usd[:3, :3].T, m[:3, :3] * [-1, 1, -1], atol=1e-6)
    np.testing.assert_allclose(usd[3, :3], camera.origin)
    assert APERTURE == pytest.approx(0.36)


def test_the_uv_sphere_faces_outward():
    """The UV sphere: no point-like triangle at the poles, every face wound counter-clockwise
    seen from outside (its normal along its corners' normals)."""
    from captures.scene import Sphere

    mesh = sphere_mesh(Sphere((0.0, 0.0, 0.0), 2.0), 16)
    assert len(mesh.faces) == 16 * (8 - 1) * 2
    p = mesh.positions[mesh.faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(np.linalg.norm(n, axis=1) > 1e-6)
    assert np.all(np.einsum("ij,ij->i", n, mesh.normals[mesh.faces].sum(1)) > 0)
