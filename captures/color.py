"""Colour conversions (numpy): colour temperature to linear Rec.709 RGB."""

from __future__ import annotations

import numpy as np

# CIE XYZ -> linear Rec.709 / sRGB primaries, D65 white (IEC 61966-2-1).
XYZ_TO_REC709 = np.array(
    [
        [3.2404542, -1.5371385, -0.4985314],
        [-0.9692660, 1.8760108, 0.0415560],
        [0.0556434, -0.2040259, 1.0572252],
    ]
)


def planckian_xy(kelvin: float) -> tuple[float, float]:
    """CIE 1931 chromaticity of a black body (Kang et al. 2002 cubic fits, 1667 K to 25000 K)."""
    t = float(kelvin)
    if not 1667.0 <= t <= 25000.0:
        raise ValueError(
            f"= {kelvin:g} K is outside [1667, 25000] K (black-body fit's range); give a "
            "temperature in it, or a color"
        )
    if t <= 4000.0:
        x = -0.2661239e9 / t**3 - 0.2343589e6 / t**2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t**3 + 2.1070379e6 / t**2 + 0.2226347e3 / t + 0.240390
    if t <= 2222.0:
        y = -1.1063814 * x**3 - 1.34811020 * x**2 + 2.18555832 * x - 0.20219683
    elif t <= 4000.0:
        y = -0.9549476 * x**3 - 1.37418593 * x**2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x**3 - 5.87338670 * x**2 + 3.75112997 * x - 0.37001483
    return x, y


def blackbody_rgb(kelvin: float) -> tuple[float, float, float]:
    """Linear Rec.709 RGB of a black body's colour with luminance Y = 1 (negative components, out
    of the Rec.709 gamut below ~1900 K, are clipped to 0)."""
    x, y = planckian_xy(kelvin)
    xyz = np.array([x / y, 1.0, (1.0 - x - y) / y])
    rgb = np.clip(XYZ_TO_REC709 @ xyz, 0.0, None)
    return tuple(float(c) for c in rgb)
