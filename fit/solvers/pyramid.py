"""Coarse-to-fine textures for Adam: each free texture's texels as the sum of itself and coarser
copies of it.

A texel's gradient is its few pixels' Monte Carlo noise, so Adam, whose steps are about its rate
whatever the gradient's size, moves every texel of a texture by its own noise and the texture's
broad shape slowly. Here the solver's coordinates are the texels plus `levels` coarser grids per
texture, each half the last one's size (rounded up), in the unconstrained space: a texel's
coordinate is its own plus the coarse cells' it lies in (nearest, not interpolated). A coarse
cell's gradient sums its texels' (the gradients of many pixels at once), so Adam moves the
texture's broad shape at the rate of its clearest signal and the fine texels add the detail:
coarse to fine in one phase, with no change of resolution between phases. The coarse grids start
at zero: the start is the texels'.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np


@dataclass(frozen=True)
class Grid:
    """A coarse grid of one texture: its texels' offset in u, the texture's shape, the level
    (cells of 2^level x 2^level texels), its offset among the coarse coordinates, its shape."""

    offset: int
    shape: tuple[int, int, int]
    level: int
    start: int
    cells: tuple[int, int]

    @property
    def size(self) -> int:
        return self.cells[0] * self.cells[1] * self.shape[2]


class Pyramid:
    """The coarse grids of every free texture of `free` (each texture until its grid would be a
    single cell or `levels` of them)."""

    def __init__(self, free, levels: int):
        self.grids: list[Grid] = []
        offset, start = 0, 0
        for f in free:
            if f.shape:
                height, width, _ = f.shape
                for level in range(1, levels + 1):
                    cells = (-(-height // 2**level), -(-width // 2**level))
                    if cells == (1, 1):
                        break
                    grid = Grid(offset, tuple(f.shape), level, start, cells)
                    self.grids.append(grid)
                    start += grid.size
            offset += f.size
        self.extra = start

    def start(self, u) -> np.ndarray:
        """The solver's coordinates of `u`: its own, then the coarse grids at zero."""
        return np.concatenate([np.asarray(u, np.float32), np.zeros(self.extra, np.float32)])

    def expand(self, z):
        """`u` of the solver's coordinates `z` (a JAX array): each texel plus its cells; `z`
        itself without grids."""
        if not self.grids:
            return z
        n = z.shape[0] - self.extra
        u = z[:n]
        for g in self.grids:
            height, width, channels = g.shape
            coarse = z[n + g.start : n + g.start + g.size].reshape(*g.cells, channels)
            block = 2**g.level
            fine = jnp.repeat(jnp.repeat(coarse, block, axis=0), block, axis=1)[:height, :width]
            u = u.at[g.offset : g.offset + fine.size].add(fine.reshape(-1))
        return u

    def owners(self) -> np.ndarray:
        """For each coarse coordinate, the index in u of a texel of its texture (the first), so
        that what holds a texture holds its grids."""
        out = np.zeros(self.extra, np.int64)
        for g in self.grids:
            out[g.start : g.start + g.size] = g.offset
        return out
