"""USD: the fitted object's stage (`--with-scene`): what layerfit renders the material in, from
the capture, beside the exported `material.usda`.

`scene.usda` (metres and Z up, as layerfit's world: `metersPerUnit` 1, `upAxis` Z; a DiLiGenT
capture's world is in its image's pixels, its scale unknown) holds:

- `/Scene/Object`: the object as a triangle mesh (`object.usdc`, binary, referenced) with the
  normals the renderer shades by and its UVs as the primvar `st`, laid out as an OBJ file stores
  them (the exported maps' layout: v = 1 - Mitsuba's v). The analytic sphere becomes a UV sphere
  of `SPHERE_SEGMENTS` x `SPHERE_SEGMENTS / 2` quads, its vertices on the sphere and Mitsuba's
  UVs (u around z from +x, v from the top); the cup and a normal map's height field are the
  meshes layerfit renders (a height field's UVs are its image coordinates, (x / W, y / H) from
  the top-left corner, so its `st` is (x / W, 1 - y / H)); an OBJ is read as Mitsuba reads it
  (its welded vertices, normals: the file's, interpolated, or flat per face with
  `face_normals`).
- `/Scene/Looks/Material`: `material.usda` referenced, bound to the object.
- `/Scene/Cameras/<view>`: one `UsdGeom.Camera` per distinct camera (views sharing one, as in
  photometric stereo, share its prim; `customData` lists them), looking from `origin` at
  `target` with `up`. Perspective: a 36 mm wide aperture (`APERTURE`, in the schema's tenths of
  a scene unit) and the focal length of the horizontal field of view, the vertical aperture of
  the image's aspect, a calibrated principal point as aperture offsets; a thin lens as `fStop`
  (the focal length over the aperture's diameter) and `focusDistance`. Orthographic: apertures
  of the view's extent (tenths of a scene unit). Clipping as layerfit renders (`clip_range`).
- `/Render/<view>`: a `UsdRender.Settings` per camera with the image's resolution (USD's
  cameras have none); the stage's `renderSettingsPrimPath` names the first.
- `/Scene/Lights`: rectangles as `RectLight`s (one-sided, emitting along their local -Z, their
  `intensity` x `color` the radiance), point lights as small `SphereLight`s (USD has no point
  light: radius `POINT_RADIUS` of the distance to the object, radiance I / (pi r^2), so their
  intensity I is kept), directional lights as `DistantLight`s (`angle` 0, `normalize` on: the
  intensity is the irradiance), the environment as a `DomeLight` (a constant's radiance, or the
  map copied beside the stage, lat-long, scaled and turned as layerfit turns it). Where views
  have their own lights (photometric stereo), a variant set `view` on `/Scene/Lights` holds each
  view's, the first selected.

`treatAsPoint` is not set on the point lights: UsdLux gives a zero-radius sphere no intensity
(radiance x area), and Blender's importer drops the radius where it is set. What a renderer
makes of the rest varies: Blender 5.0 reads the rectangles, spheres and the dome as their
radiance (its renders agree with layerfit's, docs/exports.md), but a distant light at 4 x its
intensity ("approximately matches Karma", its importer says) and an orthographic camera's
aperture as scene units (10 x wide). `LIMITS` says what the stage cannot hold.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from captures.capture import Capture
from captures.errors import InputError
from captures.geometry import MeshData, cup_mesh
from captures.scene import (
    Camera,
    Cup,
    DirectionalLight,
    EnvMap,
    MeshArrays,
    ObjFile,
    PointLight,
    RectLight,
    Sphere,
    bounding_sphere,
)

#: The stage's file, and its mesh's (binary: a height field has 10^5 vertices).
FILE = "scene.usda"
OBJECT_FILE = "object.usdc"
#: Quads around the analytic sphere's axis (half as many from pole to pole): its faces lie
#: within 7.5e-5 radii of the sphere (0.008 pixels across a 200-pixel-wide view of it).
SPHERE_SEGMENTS = 256
#: A perspective camera's horizontal aperture, in the schema's tenths of a scene unit: 36 mm (a
#: full-frame sensor), so the focal length reads as a photographer's (a 40-degree view: 49.5 mm).
APERTURE = 0.36
#: A point light's sphere radius as a share of its distance to the object's bounding sphere's
#: centre: its shadows are as sharp as a point's within a thousandth of that distance.
POINT_RADIUS = 1e-3
#: What the stage cannot hold of layerfit's scene (the stage's `comment`, beside the material's).
LIMITS = (
    "layerfit's scene as USD holds it: point lights are small sphere lights of the same "
    "intensity (USD has no point light), the analytic sphere a UV sphere; the integrator, its "
    "path depth and the pixel filter (a box of one pixel) are not held; a Mitsuba thin lens's "
    "aperture radius is an f-stop of the 36 mm aperture's focal length."
)


@dataclass(frozen=True)
class Surface:
    """A triangle mesh as the stage holds it: `positions` (N, 3), `faces` (M, 3), `normals`
    (N, 3) per vertex or None (flat: each face its own), `st` (N, 2) as an OBJ file stores UVs
    (v up) or None (the mesh has none)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    st: np.ndarray | None


def sphere_mesh(sphere: Sphere, segments: int = SPHERE_SEGMENTS) -> MeshData:
    """A UV sphere with Mitsuba's UVs (u = atan2(y, x) / 2 pi from +x, v = theta / pi from the
    +z pole), normals outward, faces wound counter-clockwise seen from outside; the seam's and
    the poles' vertices repeated, one per UV."""
    rings = segments // 2
    theta = np.linspace(0.0, np.pi, rings + 1)[:, None]
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)[None, :]
    normals = np.stack(
        np.broadcast_arrays(
            np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)
        ),
        -1,
    ).reshape(-1, 3)
    u, v = np.meshgrid(phi[0] / (2 * np.pi), theta[:, 0] / np.pi)
    idx = np.arange((rings + 1) * (segments + 1)).reshape(rings + 1, segments + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # the pole rows' other triangle is a point: (a, d, b) at the top, (a, c, d) at the bottom
    faces = np.concatenate([np.stack([a, c, d], -1)[:-1], np.stack([a, d, b], -1)[1:]])
    positions = np.asarray(sphere.center, float) + sphere.radius * normals
    uvs = np.stack([u, v], -1).reshape(-1, 2)
    return MeshData(positions, faces.reshape(-1, 3).astype(np.uint32), normals, uvs)


def object_surface(geometry) -> Surface:
    """The capture's object as the stage holds it (`st` = (u, 1 - v) of the UVs layerfit
    renders with, which are Mitsuba's: it flips an OBJ's v when it loads one)."""
    if isinstance(geometry, ObjFile):
        import mitsuba as mi

        loaded = mi.load_dict(
            {"type": "obj", "filename": str(geometry.path), "face_normals": geometry.face_normals}
        )
        params = mi.traverse(loaded)
        data = MeshData(
            np.asarray(params["vertex_positions"], np.float64).reshape(-1, 3),
            np.asarray(params["faces"], np.int64).reshape(-1, 3),
            np.asarray(params["vertex_normals"], np.float64).reshape(-1, 3)
            if loaded.has_vertex_normals()
            else None,
            np.asarray(params["vertex_texcoords"], np.float64).reshape(-1, 2)
            if loaded.has_vertex_texcoords()
            else None,
        )
    elif isinstance(geometry, Sphere):
        data = sphere_mesh(geometry)
    elif isinstance(geometry, Cup):
        data = cup_mesh(geometry.shape)
    elif isinstance(geometry, MeshArrays):
        data = geometry.data
    else:
        raise TypeError(f"unknown geometry {geometry!r}")
    st = None if data.uvs is None else np.stack([data.uvs[:, 0], 1.0 - data.uvs[:, 1]], -1)
    return Surface(data.positions, data.faces, data.normals, st)


def look_at(camera: Camera) -> np.ndarray:
    """The camera's local-to-world matrix for USD (row vectors): x right in the image, y up,
    looking along -z, at `origin` (Mitsuba's `look_at` frame with x and z negated)."""
    origin = np.asarray(camera.origin, float)
    forward = np.subtract(camera.target, origin)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    return frame(right, np.cross(right, forward), -forward, origin)


def frame(x, y, z, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The 4x4 row-vector matrix (USD's) whose local axes are `x`, `y`, `z` at `origin`."""
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = x, y, z, origin
    return m


def _transform(prim, matrix: np.ndarray) -> None:
    from pxr import Gf, UsdGeom

    UsdGeom.Xformable(prim).AddTransformOp().Set(Gf.Matrix4d(matrix.tolist()))


def _colour(light, rgb) -> None:
    """`intensity` x `color` = `rgb`, the colour's largest channel 1."""
    from pxr import Gf

    peak = float(max(rgb))
    light.CreateIntensityAttr(peak)
    light.CreateColorAttr(Gf.Vec3f(*(float(c) / peak for c in rgb)))
    light.CreateNormalizeAttr(False)


def define_camera(stage, path: str, camera: Camera, bounds) -> None:
    """A `UsdGeom.Camera` at `path` that sees what layerfit's sensor of `camera` sees."""
    from pxr import Gf, UsdGeom

    from ..render.scene import clip_range

    usd = UsdGeom.Camera.Define(stage, path)
    _transform(usd.GetPrim(), look_at(camera))
    aspect = camera.height / camera.width
    near, far = clip_range(camera, bounds)
    usd.CreateClippingRangeAttr(Gf.Vec2f(near, far))
    if camera.kind == "orthographic":
        usd.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
        width = camera.ortho_width / Gf.Camera.APERTURE_UNIT
        usd.CreateHorizontalApertureAttr(width)
        usd.CreateVerticalApertureAttr(width * aspect)
        return
    usd.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    usd.CreateHorizontalApertureAttr(APERTURE)
    usd.CreateVerticalApertureAttr(APERTURE * aspect)
    focal = APERTURE / 2 / math.tan(math.radians(camera.fov_x_deg) / 2)
    usd.CreateFocalLengthAttr(focal)
    if camera.principal_point is not None:  # the window moves against the axis's offset
        dx, dy = camera.principal_offset()
        usd.CreateHorizontalApertureOffsetAttr(dx * APERTURE)
        usd.CreateVerticalApertureOffsetAttr(-dy * APERTURE * aspect)
    if camera.aperture_radius > 0:
        focus = camera.focus_distance or float(
            np.linalg.norm(np.subtract(camera.target, camera.origin))
        )
        focal_units = focal * Gf.Camera.FOCAL_LENGTH_UNIT
        usd.CreateFStopAttr(focal_units / (2 * camera.aperture_radius))
        usd.CreateFocusDistanceAttr(focus)


def define_light(stage, path: str, light, bounds) -> None:
    """A UsdLux light at `path` of the same radiance (`LIMITS` for the point light)."""
    from pxr import UsdLux

    if isinstance(light, RectLight):
        usd = UsdLux.RectLight.Define(stage, path)
        usd.CreateWidthAttr(float(light.size[0]))
        usd.CreateHeightAttr(float(light.size[1]))
        _colour(usd, light.radiance)
        # emits along its local -z: x = u, y = v, z = -emit_direction (= u x v)
        normal = -np.asarray(light.emit_direction, float)
        _transform(usd.GetPrim(), frame(light.u_axis, light.v_axis, normal, light.center))
    elif isinstance(light, PointLight):
        distance = float(np.linalg.norm(np.subtract(light.position, bounds[0])))
        radius = POINT_RADIUS * max(distance, bounds[1])
        usd = UsdLux.SphereLight.Define(stage, path)
        usd.CreateRadiusAttr(radius)
        _colour(usd, np.asarray(light.intensity) / (math.pi * radius**2))
        _transform(usd.GetPrim(), frame((1, 0, 0), (0, 1, 0), (0, 0, 1), light.position))
    elif isinstance(light, DirectionalLight):
        usd = UsdLux.DistantLight.Define(stage, path)
        usd.CreateAngleAttr(0.0)
        _colour(usd, light.irradiance)
        usd.CreateNormalizeAttr(True)  # the intensity is the irradiance
        z = -np.asarray(light.direction, float)  # it travels along its local -z
        x = np.cross((0.0, 0.0, 1.0) if abs(z[2]) < 0.9 else (1.0, 0.0, 0.0), z)
        x /= np.linalg.norm(x)
        _transform(usd.GetPrim(), frame(x, np.cross(z, x), z))
    else:
        raise TypeError(f"unknown light {light!r}")


def define_environment(stage, path: str, environment, folder: Path) -> None:
    """A `DomeLight` of the environment (none where it is black). A map is copied beside the
    stage; the dome's lat-long frame (OpenEXR's: +y the top row, +z the centre column, +x a
    quarter to the left) is Mitsuba's envmap's, turned as layerfit turns it (+z up)."""
    from pxr import Sdf, UsdLux

    if isinstance(environment, EnvMap):
        name = "environment" + Path(environment.path).suffix.lower()
        shutil.copyfile(environment.path, folder / name)
        dome = UsdLux.DomeLight.Define(stage, path)
        dome.CreateTextureFileAttr(Sdf.AssetPath(f"./{name}"))
        dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
        dome.CreateIntensityAttr(float(environment.scale))
        dome.CreateNormalizeAttr(False)
        dome.AddRotateXOp().Set(90.0)
    elif any(environment):
        _colour(UsdLux.DomeLight.Define(stage, path), environment)


def _names(capture: Capture) -> list[str]:
    """A prim name per view (its own where it is one, else `view_<name>`), unique."""
    from pxr import Tf

    out: list[str] = []
    for view in capture.views:
        name = Tf.MakeValidIdentifier(view.name)
        if name != view.name:
            name = Tf.MakeValidIdentifier(f"view_{view.name}")
        while name in out:
            name += "_"
        out.append(name)
    return out


def _mesh(path: Path, surface: Surface) -> None:
    """`path` (a new layer) holding the mesh `/Object`, its default prim."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mesh = UsdGeom.Mesh.Define(stage, "/Object")
    stage.SetDefaultPrim(mesh.GetPrim())
    points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(surface.positions, np.float32))
    faces = np.ascontiguousarray(surface.faces, np.int32)
    mesh.CreatePointsAttr(points)
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a polygon mesh, as rendered
    normals = surface.normals
    interpolation = UsdGeom.Tokens.vertex
    if normals is None:  # flat: each face's normal at its corners
        p = np.asarray(surface.positions, float)
        n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        normals, interpolation = np.repeat(n, 3, axis=0), UsdGeom.Tokens.faceVarying
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, np.float32)))
    mesh.SetNormalsInterpolation(interpolation)
    if surface.st is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
        )
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(surface.st, np.float32)))
    stage.GetRootLayer().Save()


def reads_uvs(material) -> bool:
    """Whether a composed material reads the primvar `st` (it has maps)."""
    from pxr import Usd, UsdShade

    return any(
        UsdShade.Shader(prim).GetIdAttr().Get() == "UsdPrimvarReader_float2"
        for prim in Usd.PrimRange(material.GetPrim())
        if prim.IsA(UsdShade.Shader)
    )


def export(capture: Capture, material_file: str, folder: Path) -> Path:
    """Write `scene.usda` (and `object.usdc`, an environment map) into `folder`, which holds the
    exported material `material_file`; the stage's path."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender, UsdShade, Vt

    scene = capture.scene
    bounds = bounding_sphere(scene.geometry)
    surface = object_surface(scene.geometry)
    path = folder / FILE
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetMetadata("comment", LIMITS)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.LinearUnits.meters)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Scene")
    stage.SetDefaultPrim(root.GetPrim())

    UsdGeom.Scope.Define(stage, "/Scene/Looks")
    looks = stage.DefinePrim("/Scene/Looks/Material")
    looks.GetReferences().AddReference(f"./{material_file}")
    material = UsdShade.Material(looks)
    if surface.st is None and reads_uvs(material):
        raise InputError(
            f"{scene.geometry.path}: the OBJ has no texture coordinates, and the material's maps "
            "need them: unwrap it (e.g. Blender: UV > Smart UV Project) and export it with UVs"
        )
    _mesh(folder / OBJECT_FILE, surface)
    obj = stage.DefinePrim("/Scene/Object")
    obj.GetReferences().AddReference(f"./{OBJECT_FILE}")
    UsdShade.MaterialBindingAPI.Apply(obj).Bind(material)

    names = _names(capture)
    UsdGeom.Scope.Define(stage, "/Scene/Cameras")
    UsdGeom.Scope.Define(stage, "/Render")
    cameras: dict[Camera, tuple[str, list[str]]] = {}
    for name, view in zip(names, capture.views, strict=True):
        cameras.setdefault(view.camera, (name, []))[1].append(view.name)
    for camera, (name, views) in cameras.items():
        camera_path = f"/Scene/Cameras/{name}"
        define_camera(stage, camera_path, camera, bounds)
        stage.GetPrimAtPath(camera_path).SetCustomDataByKey("layerfit:views", Vt.StringArray(views))
        settings = UsdRender.Settings.Define(stage, f"/Render/{name}")
        settings.CreateResolutionAttr(Gf.Vec2i(camera.width, camera.height))
        settings.CreatePixelAspectRatioAttr(1.0)
        settings.CreateCameraRel().SetTargets([Sdf.Path(camera_path)])
    first = next(iter(cameras.values()))[0]
    stage.SetMetadata("renderSettingsPrimPath", f"/Render/{first}")

    lights = UsdGeom.Scope.Define(stage, "/Scene/Lights").GetPrim()
    define_environment(stage, "/Scene/Lights/Environment", scene.environment, folder)
    if all(view.lights is None for view in capture.views):
        for i, light in enumerate(scene.lights):
            define_light(stage, f"/Scene/Lights/Light_{i}", light, bounds)
    else:  # photometric stereo: each view its own lights
        variants = lights.GetVariantSets().AddVariantSet("view")
        for name, view in zip(names, capture.views, strict=True):
            variants.AddVariant(name)
            variants.SetVariantSelection(name)
            with variants.GetVariantEditContext():
                own = view.lights if view.lights is not None else scene.lights
                for i, light in enumerate(own):
                    define_light(stage, f"/Scene/Lights/Light_{i}", light, bounds)
        variants.SetVariantSelection(names[0])
    stage.GetRootLayer().Save()
    return path
