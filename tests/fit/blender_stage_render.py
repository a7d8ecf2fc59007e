"""Render a `layerfit export --with-scene` stage's camera in Blender (bpy, Cycles): everything
(mesh, material, camera, lights, world) from the stage alone.

Run by the Python of the Blender venv (`.venv-blender`, made by `scripts/setup.sh
--with-blender`), never imported by the tests' own Python (bpy pins NumPy < 2):

    python blender_stage_render.py SCENE_USDA CAMERA WIDTH HEIGHT OUT_EXR SPP

`CAMERA` is the camera prim's name, `WIDTH` x `HEIGHT` its render settings' resolution (Blender
does not import `UsdRender.Settings`; the test reads it with pxr). Only the renderer's settings
are Blender's own, as in blender_render.py: a box pixel filter of width 1, 8 bounces, no
denoising, the Standard view transform. A world is made before the import: Blender's importer
turns the first dome light into the world's background only into an existing world."""

from __future__ import annotations

import sys
from pathlib import Path

import bpy
from blender_render import render  # beside this script: on sys.path when it runs


def main(usda: Path, camera: str, width: int, height: int, out: Path, spp: int) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.world = bpy.data.worlds.new("world")
    bpy.ops.wm.usd_import(filepath=str(usda))
    cameras = {o.name: o for o in scene.objects if o.type == "CAMERA"}
    scene.camera = cameras[camera]

    render(scene, width, height, out, spp)


if __name__ == "__main__":
    usda, camera, width, height, out, spp = sys.argv[1:7]
    main(Path(usda), camera, int(width), int(height), Path(out), int(spp))
