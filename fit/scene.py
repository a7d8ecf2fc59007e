"""Turn a `captures.Scene` and a material (a Mitsuba BSDF dict) into Mitsuba scene dicts."""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from captures import Camera, RectLight, Scene


def sensor_dict(camera: Camera, spp: int) -> dict:
    """A perspective sensor with a box pixel filter (the peers' convention)."""
    return {
        "type": "perspective",
        "fov": camera.fov_x_deg,
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(
            origin=camera.origin, target=camera.target, up=camera.up
        ),
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": "independent", "sample_count": spp},
    }


def rect_light_dict(light: RectLight) -> dict:
    """Mitsuba's `rectangle` spans [-1, 1]^2 with normal +z: scale by size/2 along u and v and map
    +z to the emission direction (the normal transforms to `emit_direction` since it is orthogonal
    to both edges)."""
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
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(light.radiance)}},
    }


def geometry_dict(scene: Scene, bsdf: dict) -> dict:
    if scene.geometry == "sphere":
        return {"type": "sphere", "bsdf": bsdf}
    return {"type": "obj", "filename": str(scene.geometry), "bsdf": bsdf}


def scene_dict(scene: Scene, bsdf: dict, view: int = 0, spp: int = 64) -> dict:
    """A Mitsuba scene dict of one view: the object with `bsdf` (its id is `bsdf["id"]`, if any),
    the lights, the environment and a `prb` integrator."""
    out = {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": scene.max_depth},
        "sensor": sensor_dict(scene.cameras[view], spp),
        "object": geometry_dict(scene, bsdf),
    }
    for i, light in enumerate(scene.lights):
        out[f"light_{i}"] = rect_light_dict(light)
    if any(scene.environment):
        out["environment"] = {
            "type": "constant",
            "radiance": {"type": "rgb", "value": list(scene.environment)},
        }
    return out


def coverage_dict(scene: Scene, view: int = 0, spp: int = 64) -> dict:
    """A scene whose render is each pixel's object coverage in [0, 1] (the object emits 1, nothing
    else is lit), through the same camera and pixel filter as `scene_dict`."""
    obj = geometry_dict(
        scene, {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}
    )
    obj["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},  # emitters seen directly, nothing else
        "sensor": sensor_dict(scene.cameras[view], spp),
        "object": obj,
    }
