"""Render time of our BSDFs against Mitsuba's built-ins, and of the cup's layer stack against
its layers alone."""

from __future__ import annotations

import dataclasses
import statistics
import time

import mitsuba as mi
import numpy as np

from ..config import load_render_config
from ..render import load_scene, scene_dict
from .common import CUP_SCENE, DEFAULT_SCENE, Table, machine, ticker


def _timed(scene: mi.Scene, spp: int, seed: int) -> float:
    start = time.perf_counter()
    np.asarray(mi.render(scene, spp=spp, seed=seed))  # forces the lazy result
    return time.perf_counter() - start


def _interleaved(scenes: dict, spp: int, repeats: int, progress, label: str) -> dict[str, list]:
    """Times of `repeats` renders of each scene, interleaved (so that drift hits all alike), after
    an untimed warm-up each (first renders compile kernels)."""
    advance = ticker(progress, label, repeats * len(scenes))
    times: dict[str, list[float]] = {name: [] for name in scenes}
    for scene in scenes.values():
        _timed(scene, spp, 0)
    for i in range(repeats):
        for name, scene in scenes.items():
            times[name].append(_timed(scene, spp, i + 1))
            advance()
    return times


def _timings(scene, materials: dict, spp: int, repeats: int, progress, label: str):
    """(each material's render times, their medians): `materials` rendered in `scene`."""
    scenes = {name: load_scene(scene_dict(scene, m, 0, spp)) for name, m in materials.items()}
    times = _interleaved(scenes, spp, repeats, progress, label)
    return times, {name: statistics.median(t) for name, t in times.items()}


def _interleaved_note(repeats: int) -> str:
    return f"median of {repeats} interleaved renders after one untimed warm-up each"


def bsdf_speed_table(spp: int = 64, repeats: int = 7, progress=None) -> Table:
    """Render time of our BSDFs vs Mitsuba's built-ins with matching parameters, same scene.

    `glaze` is compared with `principled` (the built-in with a Fresnel-weighted specular lobe over
    a diffuse base), `oren_nayar` with `diffuse`.
    """
    cfg = load_render_config(DEFAULT_SCENE)
    glaze = cfg.material.bsdf
    pigment = glaze["pigment"]
    principled = {
        "type": "principled",
        "base_color": pigment,
        "roughness": float(np.sqrt(glaze["roughness"])),  # principled's roughness r: alpha = r^2
        "eta": glaze["ior"],
    }
    # name: (BSDF, reference name)
    bsdfs = {
        "principled": (principled, "principled"),
        "glaze paper/schlick": (glaze, "principled"),
        "glaze paper/exact": ({**glaze, "fresnel": "exact"}, "principled"),
        "glaze reciprocal/schlick": ({**glaze, "coupling": "reciprocal"}, "principled"),
        "diffuse": ({"type": "diffuse", "reflectance": pigment}, "diffuse"),
        "oren_nayar sigma 0.5": (
            {"type": "oren_nayar", "reflectance": pigment, "sigma": 0.5},
            "diffuse",
        ),
    }
    materials = {name: b for name, (b, _) in bsdfs.items()}
    times, median = _timings(cfg.scene, materials, spp, repeats, progress, "bench: BSDF speed")
    cam = cfg.scene.cameras[0]
    rows = [
        [
            name,
            f"{median[name] * 1e3:.1f}",
            f"{min(times[name]) * 1e3:.1f}",
            ref,
            f"{median[name] / median[ref]:.3f}",
        ]
        for name, (_, ref) in bsdfs.items()
    ]
    return Table(
        title=f"BSDF render time: glazed-sphere scene, {cam.width}x{cam.height}, {spp} spp, prb",
        columns=["BSDF", "median ms", "min ms", "reference", "time / reference"],
        rows=rows,
        notes=[_interleaved_note(repeats), machine()],
    )


def cup_speed_table(spp: int = 64, repeats: int = 5, size: int = 256, progress=None) -> Table:
    """Render time of the paper's cup (configs/cup.toml) at `size`^2, and of each of its layers
    alone as the whole material: the stack's cost relative to its most expensive layer."""
    cfg = load_render_config(CUP_SCENE)
    camera = dataclasses.replace(cfg.scene.cameras[0], width=size, height=size)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    stack = cfg.material.bsdf
    materials = {"cup: 4-layer stack": stack}
    materials |= {f"{name} alone": stack[name] for name in stack["layers"].split(",")}
    times, median = _timings(scene, materials, spp, repeats, progress, "bench: cup layers")
    slowest = max((n for n in median if n.endswith("alone")), key=median.get)
    rows = [
        [
            name,
            f"{median[name] * 1e3:.0f}",
            f"{min(times[name]) * 1e3:.0f}",
            f"{median[name] / median[slowest]:.2f}",
        ]
        for name in materials
    ]
    return Table(
        title=f"Cup render time: {size}x{size}, {spp} spp, prb, max depth {scene.max_depth}",
        columns=["material", "median ms", "min ms", f"time / {slowest}"],
        rows=rows,
        notes=[
            _interleaved_note(repeats),
            "a layer alone: its BSDF as the whole material (no masks, no bump)",
            machine(),
        ],
    )
