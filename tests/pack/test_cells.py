"""The compiled linked-cell neighbour search (kernels.cell_pairs) against the k-d tree search
(parjam.net.system), and the force field that uses it."""

import numpy as np
import pytest

from parjam.pack import kernels
from parjam.pack.packing import random_packing
from parjam.net.system import neighbour_pairs, neighbour_pairs_touching, wrap


@pytest.mark.parametrize("d, n, phi, dispersity", [(3, 700, 0.66, "mono"), (2, 900, 0.84, "bi"),
                                                   (3, 400, 0.30, "poly"), (2, 60, 0.7, "bi")])
def test_cell_search_finds_the_k_d_tree_pairs(d, n, phi, dispersity):
    """Same pairs, same (i, j) order, for every particle block (one rank's, thin ones, empty,
    all), from unwrapped positions folded first; dense and dilute, mono-, bi- and polydisperse,
    2D and 3D; a box of fewer than 3 cells a side has no cell search (None)."""
    if kernels.library() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    pack = random_packing(d, n, phi, 2.0, dispersity, 1.4, np.random.default_rng(n))
    cut = pack.diam.max() * 1.2
    pos = wrap(pack.pos + pack.L * np.random.default_rng(1).integers(-1, 2, pack.pos.shape),
               pack.L)
    full = neighbour_pairs(pos, pack.L, cut)
    assert len(full) > 2 * n if phi > 0.5 else len(full) > 0
    blocks = [(0, n), (0, 1), (n // 2, n // 2), (n // 3, n // 3 + n // 8), (n - n // 8, n)]
    for lo, hi in blocks:
        got = kernels.cell_pairs(pos, pack.L, cut, lo, hi)
        assert np.array_equal(got, neighbour_pairs_touching(pos, pack.L, cut, lo, hi)), (lo, hi)
    assert kernels.cell_pairs(pos, pack.L, pack.L / 2.9, 0, n) is None


def test_cell_search_at_three_cells_a_side():
    """The smallest box the cell search takes (3 cells a side: every neighbour cell is another
    cell, and the periodic images meet): the k-d tree's pairs exactly."""
    rng = np.random.default_rng(3)
    L, cut = 3.3, 1.05
    pos = rng.uniform(0, L, (120, 3))
    got = kernels.cell_pairs(pos, L, cut, 0, 120)
    assert got is not None and len(got) > 100
    assert np.array_equal(got, neighbour_pairs(pos, L, cut))
