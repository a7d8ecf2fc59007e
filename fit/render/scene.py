"""Turn a `captures.Scene` and a material (a Mitsuba BSDF dict) into Mitsuba scene dicts."""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from captures import Camera, Scene
from captures.errors import listing
from captures.geometry import MeshData, cup_mesh
from captures.scene import (
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
from captures.schema import geometry_to_table

from ..material import Material

#: Traverse-key prefix of the object's material in a scene built by `scene_dict`.
MATERIAL_PREFIX = "object.bsdf."


def load_scene(scene: dict) -> mi.Scene:
    """Mitsuba's scene of a scene dict, its shapes and emitters in the dict's order.

    `mi.load_dict` runs the parser's optimisations, and one of them, `merge_meshes` (shapes that
    share a material combined), lists the shapes in an order that varies from one load of a dict
    to the next within a process (measured: the two lights of a scene swapped in 7 of 100 loads).
    The emitter a random number picks follows that order, so a render at the same seed drew
    other samples (an image mean 4 % off at 16 spp, an equally valid estimate): renders and fits
    were not repeatable. Without it the order is the dict's (100 of 100 loads). The other,
    `merge_equivalent` (identical objects shared), stays: without it too, a frozen Jacobian of
    emitter scales replayed beside another `Renderer`'s frozen passes came out wrong at a pixel
    (the environment's column 11 % off; tests/fit/test_bound_starts.py)."""
    config = mi.parser.ParserConfig(mi.variant())
    config.merge_meshes = False
    state = mi.parser.parse_dict(config, scene)
    mi.parser.transform_all(config, state)
    return mi.parser.instantiate(config, state)


def clip_range(camera: Camera, bounds: tuple[np.ndarray, float] | None = None) -> tuple:
    """(near, far) clip distances on the scene's scale: a thousandth of the distance to the
    target or, nearer, to the far side of the object's bounding sphere `bounds` (centre,
    radius), and at least 1e4 and twice that far side (Mitsuba's defaults, 0.01 and 1e4, are
    metres: an object 5 mm from the camera, a scene in millimetres, rendered empty; a target
    set far beyond the object along the view put the near plane past it)."""
    origin = np.asarray(camera.origin, float)
    scale = float(np.linalg.norm(np.subtract(camera.target, origin)))
    reach = 0.0
    if bounds is not None:
        reach = float(np.linalg.norm(np.asarray(bounds[0], float) - origin)) + bounds[1]
        scale = min(scale, reach)
    return 1e-3 * scale, max(1e4, 1e3 * scale, 2.0 * reach)


def sensor_dict(camera: Camera, spp: int, bounds: tuple[np.ndarray, float] | None = None) -> dict:
    """A perspective (pinhole or thin-lens) or orthographic sensor, box pixel filter, its clip
    distances from the object's bounding sphere `bounds` where given (`clip_range`)."""
    to_world = mi.ScalarTransform4f().look_at(
        origin=camera.origin, target=camera.target, up=camera.up
    )
    out: dict = {
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": "independent", "sample_count": spp},
    }
    near, far = clip_range(camera, bounds)
    out.update({"near_clip": near, "far_clip": far})
    if camera.kind == "orthographic":
        half = camera.ortho_width / 2  # Mitsuba's view spans [-1, 1] horizontally
        return {
            **out,
            "type": "orthographic",
            "to_world": to_world @ mi.ScalarTransform4f().scale([half, half, 1.0]),
        }
    out.update(
        {"type": "perspective", "fov": camera.fov_x_deg, "fov_axis": "x", "to_world": to_world}
    )
    if camera.principal_point is not None:  # a pinhole's (the schema refuses it with a lens)
        x, y = camera.principal_offset()
        out.update({"principal_point_offset_x": x, "principal_point_offset_y": y})
    if camera.aperture_radius > 0:
        focus = camera.focus_distance or float(
            np.linalg.norm(np.subtract(camera.target, camera.origin))
        )
        out.update(
            {"type": "thinlens", "aperture_radius": camera.aperture_radius, "focus_distance": focus}
        )
    return out


def rect_light_dict(light: RectLight) -> dict:
    """Mitsuba's `rectangle` spans [-1, 1]^2 with normal +z: scale by size/2 along u and v and map
    +z to the emission direction (the normal transforms to `emit_direction` since it is orthogonal
    to both edges).

    The card gets a `null` BSDF: rays pass through it both ways, as through an area light in
    Cycles (invisible from behind). Without it Mitsuba gives the shape a default
    diffuse BSDF whose back side is black, so a camera behind the light saw a black card over the
    object. Emission from the front is still found by BSDF-sampled rays (MIS weighted as before;
    a null surface counts as a delta vertex, so paths continuing through it stay unbiased) and by
    emitter sampling. Shadow rays still stop at the card (`path`/`prb` test geometry only), but a
    BSDF-sampled path through it counts what lies behind with full weight, so expected values
    do not change, only the noise in the card's shadow. Seen from the front by the camera the
    emission stays visible (Mitsuba has no per-shape camera visibility)."""
    u, v, n = (
        np.asarray(x, dtype=float) for x in (light.u_axis, light.v_axis, light.emit_direction)
    )
    m = np.eye(4)
    m[:3, 0] = u * light.size[0] / 2
    m[:3, 1] = v * light.size[1] / 2
    m[:3, 2] = n
    m[:3, 3] = light.center
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "bsdf": {"type": "null"},
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(light.radiance)}},
    }


def light_dict(light) -> dict:
    if isinstance(light, RectLight):
        return rect_light_dict(light)
    if isinstance(light, PointLight):
        return {
            "type": "point",
            "position": list(light.position),
            "intensity": {"type": "rgb", "value": list(light.intensity)},
        }
    if isinstance(light, DirectionalLight):
        return {
            "type": "directional",
            "direction": list(light.direction),
            "irradiance": {"type": "rgb", "value": list(light.irradiance)},
        }
    raise TypeError(f"unknown light {light!r}")


def mesh(data: MeshData, name: str, bsdf: mi.BSDF, emitter: dict | None = None) -> mi.Mesh:
    """A Mitsuba mesh from arrays, with normals and UVs."""
    props = mi.Properties()
    props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    out = mi.Mesh(
        name,
        len(data.positions),
        len(data.faces),
        props=props,
        has_vertex_normals=True,
        has_vertex_texcoords=True,
    )
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(np.ravel(data.positions).astype(np.float32))
    params["faces"] = mi.UInt32(np.ravel(data.faces).astype(np.uint32))
    params["vertex_normals"] = mi.Float(np.ravel(data.normals).astype(np.float32))
    params["vertex_texcoords"] = mi.Float(np.ravel(data.uvs).astype(np.float32))
    params.update()
    return out


def geometry_dict(scene: Scene, bsdf: mi.BSDF, emitter: dict | None = None) -> dict | mi.Mesh:
    """The object with a loaded `bsdf` (and an optional area `emitter`)."""
    geometry = scene.geometry
    if isinstance(geometry, Cup):
        return mesh(cup_mesh(geometry.shape), "cup", bsdf, emitter)
    if isinstance(geometry, MeshArrays):
        return mesh(geometry.data, "object", bsdf, emitter)
    if not isinstance(geometry, Sphere | ObjFile):
        raise TypeError(f"unknown geometry {geometry!r}")
    # a manifest's table, its file named as Mitsuba names it
    out = {"filename" if k == "file" else k: v for k, v in geometry_to_table(geometry).items()}
    out["bsdf"] = bsdf
    if emitter is not None:
        out["emitter"] = emitter
    return out


#: `trace_silhouettes` traces at most this many pixel centres a side of each view (spread over it).
BACK_FACE_SIDE = 256
#: The share of a view's object pixels seen from behind above which `back_face_warning` warns.
BACK_FACE_SHARE = 0.005
#: A pixel is seen from behind where the ray meets the back of its face (by the winding) below
#: its shading normal's horizon, or the front of a face this far below it (the cosine): normals
#: given pointing inward. The materials are black below 0 either way, but along the silhouette
#: of a coarse smooth mesh the interpolated normals dip below it by up to half the angle between
#: faces (an 8-sided tube: 22 degrees, cosine -0.38), which is no fault of the mesh's.
BACK_FACE_COSINE = -0.5


def bare_scene(scene: Scene, cameras) -> mi.Scene:
    """The object alone (a diffuse material, no lights) with every camera a sensor (1 spp),
    for tracing rays from the views."""
    bounds = bounding_sphere(scene.geometry)
    sensors = {f"sensor_{k:04d}": sensor_dict(c, 1, bounds) for k, c in enumerate(cameras)}
    bare = geometry_dict(scene, mi.load_dict({"type": "diffuse"}))
    return load_scene({"type": "scene", "object": bare, **sensors})


def trace_silhouettes(scene: Scene, cameras: list[Camera]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per camera: (the pixel centres that meet the object, those that meet it from behind, as
    `BACK_FACE_COSINE` says), as (ny, nx) booleans on a grid of at most `BACK_FACE_SIDE` a side
    spread over the image (cell (i, j): the pixel at ((j + 0.5) / nx, (i + 0.5) / ny) of the
    image's extent), traced through one bare scene of the object (lights left out) with every
    camera a sensor. The materials are one-sided: pixels met from behind render black (an open
    mesh seen from inside, a mesh whose normals point inward)."""
    loaded = bare_scene(scene, cameras)

    def trace(sensor, x, y) -> tuple[np.ndarray, np.ndarray]:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x.ravel(), y.ravel()), mi.Point2f(0.5))
        si = loaded.ray_intersect(ray)
        hit = np.asarray(si.is_valid())
        shading = np.asarray(si.wi.z)  # the cosine to the shading normal
        back = np.asarray(si.n.x * ray.d.x + si.n.y * ray.d.y + si.n.z * ray.d.z) > 0
        return hit, hit & (((shading < 0) & back) | (shading < BACK_FACE_COSINE))

    out = []
    for camera, sensor in zip(cameras, loaded.sensors(), strict=True):
        nx, ny = min(camera.width, BACK_FACE_SIDE), min(camera.height, BACK_FACE_SIDE)
        x, y = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny)
        hit, behind = trace(sensor, x, y)
        # a cell is seen from behind where a second ray in it, off both its centre's row and
        # column, agrees: a mesh edge projected onto a column of pixel centres let some of
        # them through the crack between its triangles, onto the far wall's inside (a closed
        # cylinder seen by orthographic cameras: 11 of 1728 cells, a false warning)
        if behind.any():
            behind &= trace(sensor, x + CELL_OFFSET[0] / nx, y + CELL_OFFSET[1] / ny)[1]
        out.append((hit.reshape(ny, nx), behind.reshape(ny, nx)))
    return out


#: The second ray of a traced cell, from its centre, in cells (x, y).
CELL_OFFSET = (0.23, 0.31)


def view_warnings(
    scene: Scene,
    views: list[tuple[str, Camera]],
    where: str,
    masks: list[tuple[np.ndarray, float] | None] | None = None,
) -> list[str]:
    """What the views' pixel centres traced through the object say, as lines: views that show
    no object at any traced pixel centre (an object under a pixel: cameras and mesh in other
    units, or out of view); views whose object mask (`masks`: per view, (mask, its coverage
    threshold) or None) the traced silhouette overlaps by less than `MIN_SILHOUETTE_IOU` (a
    mesh in other axes or units, cameras misplaced: the fit would explain the difference with
    the material); then views seeing more than `BACK_FACE_SHARE` of the object from behind.
    Views sharing a camera (photometric stereo's) are traced once."""
    cameras = list(dict.fromkeys(camera for _, camera in views))
    grids = dict(zip(cameras, trace_silhouettes(scene, cameras), strict=True))
    traced = {c: (int(hit.sum()), int(behind.sum())) for c, (hit, behind) in grids.items()}
    out = []
    overlaps = {}
    for (name, camera), given in zip(views, masks or [None] * len(views), strict=True):
        if given is not None and traced[camera][0]:
            overlaps[name] = _grid_iou(grids[camera][0], *given)
    if low := overlap_warning(where, overlaps, len(views)):
        out.append(low)
    empty = [name for name, camera in views if traced[camera][0] == 0]
    if empty:
        out.append(
            f"{where}: {len(empty)} of {len(views)} views show the object at none of their "
            f"traced pixel centres (in {listing(empty)}): it is smaller than a pixel there or "
            "out of view, and those views say nothing about its material; check the cameras' "
            "and the geometry's units (metres both) and where the cameras look"
        )
    message = _back_face_warning(views, where, traced)
    return out + ([message] if message else [])


#: A view whose object mask the traced silhouette overlaps less than this (intersection over
#: union at pixel centres) is warned: aligned, the shared peers' views score 0.94-0.97 and
#: DiLiGenT's ball 0.99; a Y-up mesh in a Z-up scene 0.37-0.69.
MIN_SILHOUETTE_IOU = 0.8


def overlap_warning(where: str, overlaps: dict[str, float], n_views: int) -> str | None:
    """The line for views whose object mask the object's silhouette overlaps under
    `MIN_SILHOUETTE_IOU` (`overlaps`: IoU per view name), or None."""
    low = {name: v for name, v in overlaps.items() if v < MIN_SILHOUETTE_IOU}
    if not low:
        return None
    shown = ", ".join(f"{name} {v:.2f}" for name, v in low.items())
    return (
        f"{where}: the object's silhouette overlaps the object mask of {len(low)} of {n_views} "
        f"views poorly (IoU {shown}; a match is above 0.9): check the mesh's axes (Y-up "
        "against Z-up) and units, the cameras' poses and the masks (an inverted one); "
        "`layerfit inspect` overlays them. The fit would explain the difference with the "
        "material"
    )


def _grid_iou(hit: np.ndarray, mask: np.ndarray, coverage: float) -> float:
    """Intersection over union of traced pixel centres `hit` (a grid over the image) and an
    object `mask` (the image's size; a bool, or a share above `coverage`) at the same pixels."""
    ny, nx = hit.shape
    h, w = mask.shape
    rows = np.minimum(((np.arange(ny) + 0.5) / ny * h).astype(int), h - 1)
    cols = np.minimum(((np.arange(nx) + 0.5) / nx * w).astype(int), w - 1)
    inside = np.asarray(mask)[np.ix_(rows, cols)]
    inside = inside > coverage if inside.dtype != bool else inside
    union = np.sum(hit | inside)
    return float(np.sum(hit & inside) / union) if union else 1.0


def _back_face_warning(views: list[tuple[str, Camera]], where: str, traced: dict) -> str | None:
    """A line naming the views (name, camera) that see more than `BACK_FACE_SHARE` of the object
    from behind, or None (`traced`: each camera's object and from-behind pixel counts)."""
    shares = {}
    for name, camera in views:
        hits, behind = traced[camera]
        if hits and behind > max(2, BACK_FACE_SHARE * hits):
            shares[name] = behind / hits
    if not shares:
        return None
    return (
        f"{where}: {len(shares)} of {len(views)} views see the object's faces from behind, "
        f"which render black (the materials are one-sided): up to {100 * max(shares.values()):.0f}"
        f" % of its pixels, in {listing(list(shares))}; the mesh is open there (a wall without "
        "thickness: give it thickness, e.g. Blender's Solidify), its normals point inward (flip "
        "them) or are smoothed across sharp edges (shade flat: face_normals = true, or export "
        "split normals), or the camera is inside it"
    )


#: Mitsuba's envmap has its top row towards +y; layerfit's world is z-up (cameras' `up`, the cup
#: stands on z): a quarter turn about x puts an equirectangular map's top (its sky) at +z and its
#: centre column towards -y (where the default cameras stand, facing +y). Without it a sky lit
#: the object from +y (a user's report: a camera looking up saw half the sky dark).
ENVMAP_TO_WORLD = mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0)


def environment_dict(scene: Scene) -> dict | None:
    env = scene.environment
    if isinstance(env, EnvMap):
        return {
            "type": "envmap",
            "filename": str(env.path),
            "scale": env.scale,
            "to_world": ENVMAP_TO_WORLD,
        }
    if any(env):
        return {"type": "constant", "radiance": {"type": "rgb", "value": list(env)}}
    return None


def scene_dict(scene: Scene, bsdf: Material | dict | mi.BSDF, view: int = 0, spp: int = 64) -> dict:
    """A Mitsuba scene dict of one view; the material's traverse keys are `MATERIAL_PREFIX` + its
    own keys (`material_keys`)."""
    if isinstance(bsdf, Material):
        bsdf = bsdf.bsdf
    material = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    out = {
        "type": "scene",
        "integrator": {"type": scene.integrator, "max_depth": scene.max_depth},
        "sensor": sensor_dict(scene.cameras[view], spp, bounding_sphere(scene.geometry)),
        "object": geometry_dict(scene, material),
    }
    for i, light in enumerate(scene.lights):
        out[f"light_{i}"] = light_dict(light)
    environment = environment_dict(scene)
    if environment is not None:
        out["environment"] = environment
    return out


def batch_sensor_dict(cameras, spp: int, bounds: tuple[np.ndarray, float] | None = None) -> dict:
    """One `batch` sensor rendering same-sized cameras side by side into one film (width: the
    cameras' widths together): all views of a capture in one kernel, compiled once."""
    width, height = cameras[0].width, cameras[0].height
    children = {}
    for i, camera in enumerate(cameras):
        child = sensor_dict(camera, spp, bounds)
        del child["film"], child["sampler"]
        children[f"view_{i:04d}"] = child  # names sort as the views do
    film = sensor_dict(cameras[0], spp)["film"]
    return {
        **children,
        "type": "batch",
        "film": {**film, "width": width * len(cameras), "height": height},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def coverage_dict(scene: Scene, view: int = 0, spp: int = 64) -> dict:
    """A scene whose render is each pixel's object coverage in [0, 1] (the object emits 1, nothing
    else is lit), through the same camera and pixel filter as `scene_dict`."""
    black = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}})
    emitter = {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},  # emitters seen directly, nothing else
        "sensor": sensor_dict(scene.cameras[view], spp, bounding_sphere(scene.geometry)),
        "object": geometry_dict(scene, black, emitter),
    }


def material_keys(scene: mi.Scene) -> list[str]:
    """The material's parameter keys in a loaded scene (`glaze.roughness`, `lime.mask.threshold`,
    ... for a stack; the plugin's own keys for a single BSDF)."""
    n = len(MATERIAL_PREFIX)
    return [k[n:] for k in mi.traverse(scene).keys() if k.startswith(MATERIAL_PREFIX)]
