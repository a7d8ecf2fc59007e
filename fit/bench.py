"""Benchmarks: tables of measured speed (never asserted in tests). Ratios come from one run."""

from __future__ import annotations

import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from .config import load_render_config
from .scene import scene_dict

DEFAULT_SCENE = Path(__file__).resolve().parent.parent / "configs" / "glazed-sphere.toml"


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]]
    notes: list[str]

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines + [""] + [f"- {n}" for n in self.notes]) + "\n"

    def rich(self):
        from rich.table import Table as RichTable

        table = RichTable(title=self.title, caption="\n".join(self.notes))
        for column in self.columns:
            table.add_column(column)
        for row in self.rows:
            table.add_row(*row)
        return table


def machine() -> str:
    import os

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, {mi.variant()}, mitsuba {mi.__version__}"


def _timed(scene: mi.Scene, spp: int, seed: int) -> float:
    start = time.perf_counter()
    np.asarray(mi.render(scene, spp=spp, seed=seed))  # forces the lazy result
    return time.perf_counter() - start


def bsdf_speed_table(spp: int = 64, repeats: int = 7, progress=None) -> Table:
    """Render time of `glaze` vs Mitsuba's `principled` with matching parameters, same scene."""
    cfg = load_render_config(DEFAULT_SCENE)
    glaze = cfg.material
    alpha = glaze["roughness"]
    principled = {
        "type": "principled",
        "base_color": glaze["pigment"],
        "roughness": float(np.sqrt(alpha)),  # principled's roughness r has alpha = r^2
        "eta": glaze["ior"],
    }
    bsdfs = {"glaze (paper, schlick)": glaze, "principled": principled}
    scenes = {name: mi.load_dict(scene_dict(cfg.scene, b, 0, spp)) for name, b in bsdfs.items()}
    task = progress.add_task("bench: glaze vs principled", total=repeats * len(scenes)) if progress else None
    times: dict[str, list[float]] = {name: [] for name in scenes}
    for name, scene in scenes.items():  # first renders compile kernels: not timed
        _timed(scene, spp, 0)
    for i in range(repeats):  # interleave so that drift hits both alike
        for name, scene in scenes.items():
            times[name].append(_timed(scene, spp, i + 1))
            if progress:
                progress.advance(task)
    ref = statistics.median(times["principled"])
    cam = cfg.scene.cameras[0]
    rows = [
        [name, f"{statistics.median(t) * 1e3:.1f}", f"{min(t) * 1e3:.1f}", f"{statistics.median(t) / ref:.3f}"]
        for name, t in times.items()
    ]
    return Table(
        title=f"Glaze vs principled: sphere, {cam.width}x{cam.height}, {spp} spp, prb",
        columns=["BSDF", "median ms", "min ms", "time / principled"],
        rows=rows,
        notes=[f"median of {repeats} renders after one untimed warm-up each", machine()],
    )
