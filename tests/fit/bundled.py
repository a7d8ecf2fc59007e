"""The project's bundled configs (configs/) as the tests read them."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CUP = ROOT / "configs" / "cup.toml"
SPHERE = ROOT / "configs" / "glazed-sphere.toml"


def cup_table() -> dict:
    """configs/cup.toml's [material] table, a fresh copy to change."""
    return tomllib.loads(CUP.read_text())["material"]


def cup_material():
    """The four-layer cup's material as configs/cup.toml declares it."""
    from fit.material import build_material

    return build_material(cup_table(), CUP)
