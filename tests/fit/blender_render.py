"""Render a peer scene.json's view in Blender (bpy, Cycles) with a USD file's material.

Run by the Python of the Blender venv (`.venv-blender`, made by `scripts/setup.sh
--with-blender`), never imported by the tests' own Python (bpy pins NumPy < 2):

    python blender_render.py SCENE_JSON VIEW MATERIAL_USDA OUT_EXR SPP

The scene is built as the peer targets were made: the mesh in world coordinates (Z up, metres),
a perspective camera looking from `origin` at `target` with `up` and a horizontal field of view,
one-sided rectangle lights (`radiance_rgb` = power x colour / (pi x area)), a constant world, a
box pixel filter of width 1, 8 bounces, no denoising, the Standard view transform."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import bpy
from mathutils import Matrix, Vector


def frame(x: Vector, y: Vector, z: Vector, origin: Vector) -> Matrix:
    """The world matrix whose local axes are `x`, `y`, `z` and whose origin is `origin`."""
    m = Matrix.Identity(4)
    for row in range(3):
        m[row][0], m[row][1], m[row][2], m[row][3] = x[row], y[row], z[row], origin[row]
    return m


def main(scene_json: Path, view: int, usda: Path, out: Path, spp: int) -> None:
    doc = json.loads(scene_json.read_text(encoding="utf-8-sig"))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    bpy.ops.wm.obj_import(
        filepath=str(scene_json.parent / doc["mesh"]), forward_axis="Y", up_axis="Z"
    )
    (mesh,) = [o for o in scene.objects if o.type == "MESH"]
    bpy.ops.wm.usd_import(filepath=str(usda), import_all_materials=True)
    nodes = [m for m in bpy.data.materials if m.node_tree]
    (material,) = [m for m in nodes if "Principled BSDF" in m.node_tree.nodes]
    mesh.data.materials.clear()
    mesh.data.materials.append(material)
    for o in [o for o in scene.objects if o is not mesh]:  # what the USD import brought along
        bpy.data.objects.remove(o)

    v = doc["views"][view]
    origin, target = Vector(v["origin"]), Vector(v["target"])
    forward = (target - origin).normalized()
    right = forward.cross(Vector(v["up"])).normalized()
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.matrix_world = frame(right, right.cross(forward), -forward, origin)
    camera.data.sensor_fit = "HORIZONTAL"
    camera.data.angle = math.radians(v["fov_x_deg"])
    camera.data.clip_start = 1e-3
    scene.collection.objects.link(camera)
    scene.camera = camera

    for k, light in enumerate(doc["lights"]):
        u, w = Vector(light["u_axis"]), Vector(light["v_axis"])
        sx, sy = light["size"]
        radiance = light["radiance_rgb"]
        peak = max(radiance)
        data = bpy.data.lights.new(f"light{k}", "AREA")
        data.shape, data.size, data.size_y = "RECTANGLE", sx, sy
        data.energy = peak * math.pi * sx * sy  # W: radiance = power x colour / (pi x area)
        data.color = [c / peak for c in radiance]
        lamp = bpy.data.objects.new(f"light{k}", data)
        lamp.matrix_world = frame(u, w, u.cross(w), Vector(light["center"]))  # emits along -z
        scene.collection.objects.link(lamp)

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    background = world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = (*doc["environment_radiance_rgb"], 1.0)
    background.inputs["Strength"].default_value = 1.0
    scene.world = world

    render(scene, v["width"], v["height"], out, spp)


def render(scene, width: int, height: int, out: Path, spp: int) -> None:
    """Render `scene`'s camera with Cycles on the CPU as the peer targets were: `spp` samples,
    no adaptive sampling or denoising, 8 bounces, a box pixel filter of width 1, the Standard
    view transform; a float EXR at `out`."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = spp
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 8
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.cycles.seed = 1
    scene.view_settings.view_transform = "Standard"
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(out)
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    scene_json, view, usda, out, spp = sys.argv[1:6]
    main(Path(scene_json), int(view), Path(usda), Path(out), int(spp))
