"""Coarse grids of free textures for Adam (`fit.solvers.pyramid`): the start is the texels',
a coarse cell moves exactly its block of texels, and holding a texture holds its grids."""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from fit.solvers.pyramid import Pyramid


@dataclass
class Free:  # the fields of `fit.material.Free` the pyramid reads
    shape: tuple
    size: int


FREE = [Free((), 1), Free((5, 7, 3), 105), Free((), 1), Free((4, 8, 1), 32)]


def test_the_start_is_the_texels_and_grids_halve_until_one_cell():
    pyramid = Pyramid(FREE, levels=8)
    # 5x7 -> 3x4, 2x2 (then 1x1: none); 4x8 -> 2x4, 1x2 (then 1x1)
    assert [(g.offset, g.level, g.cells) for g in pyramid.grids] == [
        (1, 1, (3, 4)),
        (1, 2, (2, 2)),
        (107, 1, (2, 4)),
        (107, 2, (1, 2)),
    ]
    assert pyramid.extra == 3 * 4 * 3 + 2 * 2 * 3 + 2 * 4 + 1 * 2
    u = np.random.default_rng(0).standard_normal(139).astype(np.float32)
    z = jnp.asarray(pyramid.start(u))
    np.testing.assert_array_equal(np.asarray(pyramid.expand(z)), u)


def test_a_coarse_cell_moves_its_block_of_texels_in_every_channel():
    pyramid = Pyramid(FREE, levels=2)
    z = pyramid.start(np.zeros(139, np.float32))
    grid = pyramid.grids[1]  # the 5x7x3 texture's 2x2 grid of 4x4 blocks
    cell = 139 + grid.start + (1 * 2 + 0) * 3 + 2  # row 1, column 0, channel 2
    z[cell] = 1.0
    u = np.asarray(pyramid.expand(jnp.asarray(z)))
    texels = u[1:106].reshape(5, 7, 3)
    want = np.zeros((5, 7, 3))
    want[4:, :4, 2] = 1.0  # rows 4.. (the last, clipped), columns 0-3
    np.testing.assert_array_equal(texels, want)
    assert u[0] == 0 and u[106] == 0 and not u[107:].any()  # the scalars, the other texture


def test_no_levels_no_grids_and_owners_name_their_texture():
    assert Pyramid(FREE, levels=0).extra == 0
    owners = Pyramid(FREE, levels=1).owners()
    assert set(owners[: 3 * 4 * 3]) == {1} and set(owners[3 * 4 * 3 :]) == {107}
