"""The spatial domain decomposition (parjam.net.domain) against brute force over the whole system:
balanced slabs, migration that loses and duplicates nothing, ghosts (periodic images, ghosts
from several ranks away, empty slabs) and the pairs found from owned + ghost particles.  Runs on
1 and 2 ranks (the MPI pass) and, through one serial test, on 3."""


import numpy as np
import pytest
from mpi4py import MPI

from parjam.net.domain import SlabDomain
from parjam.net.system import neighbour_pairs

from conftest import run_on_ranks

COMM = MPI.COMM_WORLD


def whole(n, d, seed, L):
    """The same random system on every rank; each rank starts with a strided share of it (not
    a spatial one), as after reading a file's row range."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, (n, d)) * L
    diam = 1.0 + 0.4 * (rng.uniform(size=n) < 0.5)
    mine = np.arange(COMM.rank, n, COMM.size)
    return x, diam, mine


def distributed(n, d, seed, L, bounds=None):
    x, diam, mine = whole(n, d, seed, L)
    dom = (SlabDomain.balanced(COMM, L, x[mine]) if bounds is None
           else SlabDomain(COMM, np.broadcast_to(L, (d,)), bounds))
    xo, ids, f = dom.migrate(x[mine], mine, {"diam": diam[mine], "flag": mine % 3 == 0})
    return dom, x, diam, xo, ids, f


@pytest.mark.parametrize("d", [2, 3])
def test_migrate_balances_and_keeps_every_particle(d):
    n = 3000
    L = np.array([9.0, 7.0, 8.0][:d])
    dom, x, diam, xo, ids, f = distributed(n, d, 5, L)
    every = np.sort(np.concatenate(COMM.allgather(ids)))
    assert np.array_equal(every, np.arange(n))  # none lost, none twice
    assert np.all(np.diff(ids) > 0)
    lo, hi = dom.bounds[dom.rank], dom.bounds[dom.rank + 1]
    assert np.all((xo[:, 0] >= lo) & (xo[:, 0] < hi))
    assert np.array_equal(xo, x[ids]) and np.array_equal(f["diam"], diam[ids])
    assert np.array_equal(f["flag"], ids % 3 == 0) and f["flag"].dtype == bool
    assert dom.imbalance(len(ids)) < 1.1
    assert dom.bounds[0] == 0.0 and dom.bounds[-1] == L[0]


def brute_ghosts(x, owner, bounds, rank, Lx, width):
    """(id, shift) of every image within width of slab `rank`, not the owned rows themselves."""
    got = []
    for s in (-Lx, 0.0, Lx):
        xs = x[:, 0] + s
        near = (xs + width > bounds[rank]) & (xs - width < bounds[rank + 1])
        if s == 0.0:
            near &= owner != rank
        got += [(int(k), s) for k in np.flatnonzero(near)]
    return sorted(got)


@pytest.mark.parametrize("d, frac", [(3, 0.12), (2, 0.2), (3, 0.45)])
def test_halo_is_every_image_within_the_width(d, frac):
    """Ghosts = brute force, positions are the unwrapped images, the plan is the general
    search's, pull and push are each other's transpose; frac = 0.45 of the box makes ghosts come from every rank (and from this
    rank's own far side)."""
    n = 1500
    L = np.full(d, 10.0)
    dom, x, diam, xo, ids, f = distributed(n, d, 11, L)
    width = frac * L[0]
    h = dom.halo(xo, ids, width)
    owner = dom.owner(x)
    want = brute_ghosts(x, owner, dom.bounds, dom.rank, L[0], width)
    assert sorted(zip(h.ids.tolist(), h.shift[:, 0].tolist())) == want
    # the plan (the general search's, or the neighbour-slab shortcut's when every slab is wider
    # than the halo) sends the same rows to the same ranks in the same order
    rows, dest, _ = dom.ghost_rows(xo[:, 0], width)
    assert np.array_equal(h.send_index, rows)
    assert np.array_equal(h.send_counts, np.bincount(dest, minlength=COMM.size))
    assert np.allclose(h.x, x[h.ids] + h.shift, rtol=0, atol=1e-12)
    assert np.array_equal(h.pull(f["diam"]), diam[h.ids])
    # push(1) counts how often each owned particle is somebody's ghost
    times = h.push(np.ones(h.n, dtype=np.int64), len(ids))
    counts = np.zeros(n, dtype=np.int64)
    for r in range(COMM.size):
        for k, _ in brute_ghosts(x, owner, dom.bounds, r, L[0], width):
            counts[k] += 1
    assert np.array_equal(times, counts[ids])
    moved = xo + 0.01  # a refresh after a small move (not re-wrapped)
    assert np.allclose(h.positions(moved), x[h.ids] + 0.01 + h.shift, atol=1e-12)


@pytest.mark.parametrize("d, empty", [(3, False), (2, False), (3, True)])
def test_pairs_from_owned_and_ghosts_are_the_systems_pairs(d, empty):
    """Every pair of the whole system exactly once over the ranks (owned-owned, and
    owned-ghost counted where the owned end has the smaller id), also with an empty slab."""
    n = 1200
    L = np.full(d, 9.0)
    bounds = None
    if empty and COMM.size > 1:  # rank 0's slab [0, 0) is empty; the others share the box
        bounds = np.concatenate(([0.0], np.linspace(0.0, L[0], COMM.size)))
    dom, x, diam, xo, ids, f = distributed(n, d, 3, L, bounds)
    cut = 1.3
    h = dom.halo(xo, ids, cut)
    p = dom.neighbour_pairs(xo, h, cut)
    gid = np.concatenate([ids, h.ids])
    i, j = gid[p[:, 0]], gid[p[:, 1]]
    keep = (p[:, 1] < len(ids)) | (i < j)
    mine = np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1)[keep]
    allp = np.concatenate(COMM.allgather(mine))
    allp = allp[np.lexsort((allp[:, 1], allp[:, 0]))]
    ref = neighbour_pairs(np.mod(x, L[0]), L[0], cut)
    assert np.array_equal(allp, ref)
    r = np.linalg.norm(dom.separation(np.concatenate([xo, h.x])[p[:, 0]],
                                      np.concatenate([xo, h.x])[p[:, 1]]), axis=1)
    assert np.all(r < cut)
    if empty and COMM.size > 1 and dom.rank == 0:
        assert len(ids) == 0


def test_fold_is_wrap_to_the_last_bit_and_owner_agrees():
    """``fold`` (x - L floor(x / L), the searches' fast wrap) lands in [0, L], within a few ulps
    of L of np.mod, far-away images and coordinates a hair either side of 0 and L included; the
    owner of folded positions is the owner of the unfolded ones."""
    L = np.array([7.3, 5.1, 9.7])
    rng = np.random.default_rng(4)
    x = rng.uniform(-3.0, 4.0, (4000, 3)) * L
    tiny = np.array([-1e-17, -5e-324, 0.0, 1e-300])
    x[:4] = tiny[:, None]
    x[4:8] = L - tiny[:, None]
    dom = SlabDomain.balanced(COMM, L, x)
    f = dom.fold(x)
    assert np.all((f >= 0.0) & (f <= L))
    w = dom.wrap(x)
    gap = np.abs(f - w)
    gap = np.minimum(gap, np.abs(gap - L))  # 0 and L are the same place
    assert np.all(gap <= 8 * np.spacing(L))
    away = np.all(np.minimum(f, L - f) > 1e-9 * L, axis=1)  # not on a face: the same owner
    assert np.array_equal(dom.owner(f, folded=True)[away], dom.owner(x)[away])


def test_bad_width_and_bounds_are_refused():
    L = np.full(3, 4.0)
    x = np.random.default_rng(0).uniform(0, 4.0, (40, 3))
    dom = SlabDomain.balanced(COMM, L, x)
    with pytest.raises(ValueError, match="half the box"):
        dom.halo(x[:0], np.arange(0), 2.0)
    with pytest.raises(ValueError, match="non-decreasing"):
        SlabDomain(COMM, L, np.linspace(4.0, 0.0, COMM.size + 1))


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A partition case two ranks cannot make: a middle rank whose neighbours differ, and ghosts
    from two ranks away."""
    res = run_on_ranks("test_domain.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
