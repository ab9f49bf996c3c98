"""The compiled linked-cell neighbour search (cellsearch.cell_pairs) against the k-d tree search
(parjam.net.system), and the force field that uses it."""

import numpy as np
import pytest

from parjam.pack import cellsearch, kernels
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
        got = cellsearch.cell_pairs(pos, pack.L, cut, lo, hi)
        assert np.array_equal(got, neighbour_pairs_touching(pos, pack.L, cut, lo, hi)), (lo, hi)
    assert cellsearch.cell_pairs(pos, pack.L, pack.L / 2.9, 0, n) is None


def test_cell_search_at_three_cells_a_side():
    """The smallest box the cell search takes (3 cells a side: every neighbour cell is another
    cell, and the periodic images meet): the k-d tree's pairs exactly."""
    rng = np.random.default_rng(3)
    L, cut = 3.3, 1.05
    pos = rng.uniform(0, L, (120, 3))
    got = cellsearch.cell_pairs(pos, L, cut, 0, 120)
    assert got is not None and len(got) > 100
    assert np.array_equal(got, neighbour_pairs(pos, L, cut))


def test_a_scratch_reused_by_searches_of_other_sizes_changes_nothing():
    """The engine keeps one cellsearch.Scratch for all its rebuilds: searches of a larger, then a
    smaller, then a 2D box through the same work arrays (stale contents, longer than needed,
    regrown) give the pairs of searches with fresh arrays, and the k-d tree's."""
    if kernels.library() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    scratch = cellsearch.Scratch()
    for d, n, phi in [(3, 900, 0.66), (3, 300, 0.66), (2, 700, 0.84), (3, 1500, 0.66)]:
        pack = random_packing(d, n, phi, 2.0, "mono", 1.4, np.random.default_rng(n))
        pos, cut = wrap(pack.pos, pack.L), 1.2 * pack.diam.max()
        reused = cellsearch.cell_pair_lists(pos, pack.L, cut, 0, n, 4 * n, scratch)
        fresh = cellsearch.cell_pair_lists(pos, pack.L, cut, 0, n)
        assert np.array_equal(np.stack(reused, axis=1), np.stack(fresh, axis=1)), (d, n)
        assert np.array_equal(np.stack(reused, axis=1), neighbour_pairs(pos, pack.L, cut))


@pytest.mark.parametrize("d, width", [(3, 5.0), (3, 1.3), (2, 7.7), (3, 0.9)])
def test_slab_search_with_layers_aligned_to_the_slab(d, width):
    """cellsearch.slab_pairs given the slab's bounds (its layers of cells aligned to them, the
    halo's ghosts among themselves not searched) lists the same pairs in the same order as
    without them and as the k-d tree fallback: a slab of owned points (kind 0), ghosts of other
    ranks within the cutoff on both sides (kind 2); slabs several cells wide, one cell wide,
    and narrower than a cell (the unaligned grid then)."""
    if kernels.library() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    rng = np.random.default_rng(int(10 * width) + d)
    L, cut, lo = 6.0, 1.25, 1.5
    n = int(40 * width * L ** (d - 1) / 6.0 ** (d - 1)) + 40
    x = rng.uniform(0, L, (n, d))
    x[:, 0] = lo + rng.uniform(-cut, width + cut, n) * (1 - 1e-12)
    inside = (x[:, 0] >= lo) & (x[:, 0] < lo + width)
    kind = np.where(inside, 0, 2)
    gid = rng.permutation(5 * n)[:n].astype(np.int64)
    row = np.arange(n, dtype=np.int64)
    low = np.argsort(gid, kind="stable")
    plain = cellsearch.slab_pairs(x, L, cut, row, gid, kind, low)
    aligned = cellsearch.slab_pairs(x, L, cut, row, gid, kind, low, slab=(lo, lo + width))
    tree = cellsearch.slab_pairs_numpy(x, L, cut, row, gid, kind, low)
    assert len(plain[0]) > n // 2
    for a, b, c in zip(plain, aligned, tree):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize("d, dispersity, n, width", [(3, "bi", 900, 4.0), (2, "poly", 900, 5.0),
                                                     (3, "bi", 900, 0.9), (3, "bi", 60, 0.9)])
def test_each_pair_within_its_own_reach(d, dispersity, n, width):
    """Given the diameters, both compiled searches (the periodic box's, cellsearch.cell_pair_lists,
    and a slab's, cellsearch.slab_pairs, aligned, unaligned, narrower than a cell, in a box of
    fewer than 3 cells a side) and the k-d tree fallback list exactly the pairs closer than
    their own reach (d_i + d_j) / 2 + skin, in the same order as the full lists they are
    subsets of: a third fewer pairs than the one cutoff max d + skin in a 1 : 1.4 mixture."""
    if kernels.library() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    pack = random_packing(d, n, 0.84 if d == 2 else 0.66, 2.0, dispersity, 1.4,
                          np.random.default_rng(11))
    skin = 0.2 * pack.diam.min()
    cut = pack.diam.max() + skin
    pos = wrap(pack.pos, pack.L)

    def within_reach(pairs, x):
        r = x[pairs[:, 1]] - x[pairs[:, 0]]
        r[:, 1:] -= pack.L * np.rint(r[:, 1:] / pack.L)
        if x is pos:
            r[:, 0] -= pack.L * np.rint(r[:, 0] / pack.L)
        reach = 0.5 * (diam[pairs[:, 0]] + diam[pairs[:, 1]]) + skin
        return np.linalg.norm(r, axis=1) <= reach

    diam = pack.diam
    if cellsearch.cell_search_applies(n, d, pack.L, cut):
        full = np.stack(cellsearch.cell_pair_lists(pos, pack.L, cut, 0, n), axis=1)
        short = np.stack(cellsearch.cell_pair_lists(pos, pack.L, cut, 0, n, diam=diam, skin=skin),
                         axis=1)
        assert np.array_equal(short, full[within_reach(full, pos)])
        assert len(short) < 0.8 * len(full)
    else:
        assert n < 100 and cellsearch.cell_pair_lists(pos, pack.L, cut, 0, n) is None
    # one slab of the box: owned points inside it, ghosts within the cutoff on both sides
    lo = 0.3 * pack.L
    x = pos.copy()
    x[:, 0] = np.mod(x[:, 0] - lo + cut, pack.L) + lo - cut  # open along axis 0 around the slab
    sel = np.flatnonzero(x[:, 0] < lo + width + cut)
    x, diam = x[sel], pack.diam[sel]
    kind = np.where((x[:, 0] >= lo) & (x[:, 0] < lo + width), 0, 2)
    gid = sel.astype(np.int64)
    row = np.arange(len(sel), dtype=np.int64)
    low = np.argsort(gid, kind="stable")
    args = (x, pack.L, cut, row, gid, kind, low)
    full = np.stack(cellsearch.slab_pairs(*args), axis=1)
    want = full[within_reach(full, x)]
    for got in (cellsearch.slab_pairs(*args, diam=diam, skin=skin),
                cellsearch.slab_pairs(*args, slab=(lo, lo + width), diam=diam, skin=skin),
                cellsearch.slab_pairs_numpy(*args, diam=diam, skin=skin)):
        assert np.array_equal(np.stack(got, axis=1), want)
    assert 0 < len(want) < 0.8 * len(full)
