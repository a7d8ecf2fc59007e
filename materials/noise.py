"""Procedural noise in UV space (pure Dr.Jit): tileable Perlin gradient noise and its fbm sum.

The lattice wraps with period 1 in UV at every octave, so the noise tiles across the u = 0/1 seam
of a body of revolution and can be baked to a texture for export. Deterministic for a given seed.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def _hash(ix, iy, seed: int):
    """32-bit integer hash of lattice coordinates and a seed (a 'lowbias32'-style mixer)."""
    h = (
        mi.UInt32(ix) * 0x8DA6B343
        ^ mi.UInt32(iy) * 0xD8163841
        ^ mi.UInt32(int(seed) % 2**32) * 0xCB1AB31F
    )
    h ^= h >> 16
    h *= 0x7FEB352D
    h ^= h >> 15
    h *= 0x846CA68B
    h ^= h >> 16
    return h


def _corner(ix, iy, dx, dy, seed: int):
    """Dot product of the corner's pseudo-random gradient, one of (+-1, +-1), with (dx, dy):
    sign flips chosen by two hash bits (no table lookups)."""
    h = _hash(ix, iy, seed)
    return dr.select((h & 1) == 0, dx, -dx) + dr.select((h & 2) == 0, dy, -dy)


def _wrap(i, period: int):
    return ((i % period) + period) % period


def perlin(p, period: int, seed: int = 0):
    """2D gradient noise at `p` (lattice units), periodic with `period` cells; about [-1, 1]."""
    cell = dr.floor(p)
    f = p - cell
    ix0, iy0 = _wrap(mi.Int32(cell.x), period), _wrap(mi.Int32(cell.y), period)
    ix1, iy1 = _wrap(ix0 + 1, period), _wrap(iy0 + 1, period)
    # Quintic fade: C2-continuous, so bump normals from the noise have no creases
    u = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)
    n00 = _corner(ix0, iy0, f.x, f.y, seed)
    n10 = _corner(ix1, iy0, f.x - 1.0, f.y, seed)
    n01 = _corner(ix0, iy1, f.x, f.y - 1.0, seed)
    n11 = _corner(ix1, iy1, f.x - 1.0, f.y - 1.0, seed)
    nx0 = dr.lerp(n00, n10, u.x)
    nx1 = dr.lerp(n01, n11, u.x)
    return dr.lerp(nx0, nx1, u.y)


def fbm(uv, scale: int, octaves: int, seed: int = 0):
    """Fractal sum of `octaves` Perlin octaves (lacunarity 2, gain 1/2) at `uv * scale`, mapped to
    about [0, 1] with mean 0.5. Tiles with period 1 in UV."""
    total, norm, amplitude = mi.Float(0.0), 0.0, 1.0
    for octave in range(octaves):
        cells = scale * 2**octave
        # each octave's seed wraps to 32 bits (seeds above 2^32 / 131 overflowed UInt32)
        total += amplitude * perlin(mi.Point2f(uv) * cells, cells, (seed * 131 + octave) % 2**32)
        norm += amplitude
        amplitude *= 0.5
    return 0.5 + 0.5 * total / norm
