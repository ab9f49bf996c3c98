"""The packing engine on the spatial decomposition (parjam.pack.engine.SlabEngine): its forces and
energy against the serial kernel on all pairs, after migrations across slab and periodic
boundaries, in a box of fewer cells than ranks, with a rebuild that one rank's particle
triggers, and FIRE on 1 rank against FIRE on all ranks (3 ranks: the serial run reruns this
file under $PARJAM_MPIRUN -n 3)."""


import numpy as np
import pytest
from mpi4py import MPI

from parjam.pack import cellsearch, kernels, rowops
from parjam.pack.engine import SlabEngine
from parjam.pack.fire import FireParams, fire
from parjam.pack.forces import ForceField
from parjam.pack.packing import random_packing
from parjam.net.domain import SlabDomain
from parjam.net.system import neighbour_pairs
from parjam.testing.gather import gather

from conftest import run_on_ranks

COMM = MPI.COMM_WORLD


def serial(pos, diam, L, alpha):
    """Forces and energy of every particle from all pairs (the serial kernel)."""
    pairs = neighbour_pairs(np.mod(pos, L), L, diam.max())
    out = np.zeros_like(pos)
    e = kernels.pair_forces(np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1]),
                            np.ascontiguousarray(pos), diam, L, alpha, 1.0, 0, len(pos), out)
    return out, e


def strided(pack, v=None):
    """This rank's strided share of the rows (not a spatial one)."""
    mine = np.arange(COMM.rank, pack.n, COMM.size)
    return pack.pos[mine], mine, pack.diam[mine], None if v is None else v[mine]


def engine(pack, skin=None, v=None):
    x, ids, diam, vv = strided(pack, v)
    skin = 0.2 * pack.diam.min() if skin is None else skin
    return SlabEngine(COMM, pack.L, pack.alpha, 1.0, skin, x, ids, diam, vv)


def gathered(eng, values):
    """(N, ...) values of the engine's rows on every rank (test only)."""
    ids = np.concatenate(COMM.allgather(eng.ids))
    vals = np.concatenate(COMM.allgather(np.asarray(values)))
    out = np.empty_like(vals)
    out[ids] = vals
    assert np.array_equal(np.sort(ids), np.arange(len(ids)))  # every particle once
    return out


def check(eng, pos, diam, L, alpha, s):
    f_ref, e_ref = serial(pos, diam, L, alpha)
    # the same pairs summed in the same order: bitwise
    np.testing.assert_array_equal(gathered(eng, eng.f), f_ref)
    assert s.energy == pytest.approx(e_ref, rel=1e-13, abs=1e-300)
    assert s.f2 == pytest.approx((f_ref ** 2).sum(), rel=1e-13, abs=1e-300)


def quenched(d, poly, n, phi, steps, seed=3):
    pack = random_packing(d, n, phi, 2.0, poly, 1.4, np.random.default_rng(seed))
    if steps:
        ff = ForceField(_petsc_self(), pack.diam, pack.L, d, 2.0)
        ff.set_positions(pack.pos)
        fire(ff, 1e-12, params=FireParams(max_steps=steps))
        pack.pos = np.array(gather(ff))
        ff.destroy()
    return pack


def _petsc_self():
    from parjam import env

    return env.petsc().COMM_SELF


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("poly", ["mono", "bi"])
@pytest.mark.parametrize("steps", [0, 400])
def test_forces_and_energy_equal_the_serial_kernel(d, poly, steps):
    """Random (steps = 0) and quenched (near a jammed minimum: many rattlers, contacts near
    their edge) states."""
    pack = quenched(d, poly, 300 if d == 2 else 400, 0.88 if d == 2 else 0.68, steps)
    eng = engine(pack)
    s = eng.start()
    check(eng, pack.pos, pack.diam, pack.L, pack.alpha, s)
    assert COMM.allreduce(eng.n_own) == pack.n


@pytest.mark.parametrize("d", [2, 3])
def test_particles_migrate_across_slab_and_periodic_boundaries(d):
    pack = quenched(d, "bi", 300, 0.85 if d == 2 else 0.65, 0)
    eng = engine(pack)
    eng.start()
    before = eng.n_migrated
    # move everything by 0.37 L along the slab axis and a bit along the others: most particles
    # change slab, a third crosses the periodic boundary
    shift = np.full(d, 0.013 * pack.L)
    shift[0] = 0.37 * pack.L
    eng.xu += shift
    eng.rebuild()
    s = eng.start()
    check(eng, pack.pos + shift, pack.diam, pack.L, pack.alpha, s)
    moved = COMM.allreduce(eng.n_migrated - before)
    assert moved > (pack.n // 4 if COMM.size > 1 else -1)
    # the slab owns what lies in it (positions wrapped)
    xw = np.mod(eng.xu[:, 0], pack.L)
    b = eng.domain.bounds
    assert np.all((xw >= b[COMM.rank]) & (xw <= b[COMM.rank + 1]))


def test_a_box_of_fewer_cells_than_ranks():
    """A box 2.4 cutoffs wide: on 3 ranks each slab is thinner than the cutoff and ghosts come
    from every rank, some of them twice (two periodic images)."""
    rng = np.random.default_rng(11)
    d, n = 2, 30
    L = 2.4 * 1.2
    pos = rng.uniform(0, L, (n, d))
    diam = np.where(rng.uniform(size=n) < 0.5, 1.0, 0.8)
    mine = np.arange(COMM.rank, n, COMM.size)
    eng = SlabEngine(COMM, L, 2.0, 1.0, 1.2 - diam.max(), pos[mine], mine, diam[mine])
    s = eng.start()
    f_ref, e_ref = serial(pos, diam, L, 2.0)
    np.testing.assert_array_equal(gathered(eng, eng.f), f_ref)
    assert s.energy == pytest.approx(e_ref, rel=1e-13)


def test_a_rebuild_that_one_ranks_particle_triggers_happens_everywhere():
    pack = quenched(3, "mono", 400, 0.66, 0)
    v = np.zeros_like(pack.pos)
    v[0] = [1.0, 0.3, -0.2]  # one fast particle (on whichever rank owns it)
    eng = engine(pack, v=v)
    s = eng.start()
    x0 = gathered(eng, eng.xu.copy())
    rebuilds = eng.n_rebuilds
    s = eng.step(0.05, False, 1.0, 0.0, s)  # v += dt F; x += dt v: particle 0 moves ~0.05
    assert eng.n_rebuilds == rebuilds  # not yet half the skin (0.1)
    for _ in range(3):
        s = eng.step(0.05, False, 1.0, 0.0, s)
    assert COMM.allgather(eng.n_rebuilds) == [rebuilds + 1] * COMM.size
    x = gathered(eng, eng.xu)
    assert np.abs(x - x0).max() > 0.1
    check(eng, x, pack.diam, pack.L, pack.alpha, s)


@pytest.mark.parametrize("d, poly", [(2, "bi"), (3, "mono")])
def test_fire_on_all_ranks_follows_fire_on_one(world, d, poly):
    """FIRE on the decomposition over all ranks against FIRE on one rank: the same trajectory
    to round-off (forces bitwise; the sums over particles differ in round-off)."""
    pack = random_packing(d, 500, 0.86 if d == 2 else 0.66, 2.0, poly, 1.4,
                          np.random.default_rng(5))
    out = []
    for comm in (_petsc_self(), world):
        ff = ForceField(comm, pack.diam, pack.L, d, 2.0)
        ff.set_positions(pack.pos)
        res = fire(ff, 0.0, params=FireParams(max_steps=250))
        out.append((res, np.array(gather(ff)), ff.n_rebuilds))
        ff.destroy()
    (r1, x1, n1), (rp, xp, nrp) = out
    assert r1.fire_steps == rp.fire_steps == 250 and n1 > 2
    d_ = x1 - xp
    assert np.abs(d_ - pack.L * np.rint(d_ / pack.L)).max() < 1e-9
    assert rp.energy == pytest.approx(r1.energy, rel=1e-9)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """Partition cases two ranks cannot make: a middle rank, slabs thinner than the cutoff."""
    res = run_on_ranks("test_engine_domain.py", 3, "-k", "not three")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


def test_the_numpy_slab_search_lists_the_compiled_ones_pairs(monkeypatch):
    """cellsearch.slab_pairs: the k-d tree fallback (PARJAM_KERNELS=numpy) lists the same pairs in
    the same order as the compiled cell search, in a thin box (every cell once), one of 3 cells
    a side (the smallest the half stencil takes: the periodic images of a cell's neighbours
    meet) and a wide one (on one rank the compiled list there is the fully periodic cell
    search's, cellsearch.cell_pair_lists: the same pairs in the same order as the slab search's)."""
    for n, L in ((30, 2.4 * 1.2), (150, 3.1 * 1.2), (400, None)):
        if L is None:
            pack = quenched(3, "bi", n, 0.6, 0)
            pos, diam, L = pack.pos, pack.diam, pack.L
        else:
            rng = np.random.default_rng(4)
            pos, diam = rng.uniform(0, L, (n, 3)), np.full(n, 1.0)
        mine = np.arange(COMM.rank, n, COMM.size)
        lists = []
        for kind in ("", "numpy"):
            monkeypatch.setenv("PARJAM_KERNELS", kind)
            kernels.reset()
            eng = SlabEngine(COMM, L, 2.0, 1.0, 0.2, pos[mine], mine, diam[mine])
            lists.append((eng.pi, eng.pj, eng.ids))
        monkeypatch.delenv("PARJAM_KERNELS")
        kernels.reset()
        for a, b in zip(*lists):
            np.testing.assert_array_equal(a, b)
        assert len(lists[0][0]) > 0


@pytest.mark.parametrize("numpy_kernels", [False, True])
def test_fold_owner_is_the_domains_fold_and_owner(monkeypatch, numpy_kernels):
    """rowops.fold_owner (one compiled pass) against SlabDomain.fold and .owner, bit for bit:
    positions far outside the box, multiples of L, a denormal below 0, points on the slab
    bounds and between them, in 2D and 3D, 1 to 4 slabs; and the owners of positions folded
    already (a position a hair below 0 folds to L: its owner is the last slab, not refolded)."""
    if numpy_kernels:
        monkeypatch.setenv("PARJAM_KERNELS", "numpy")
    kernels.reset()
    try:
        rng = np.random.default_rng(8)
        for d, L, P in ((3, 7.3, 1), (2, 5.0, 3), (3, 11.0, 4)):
            bounds = np.concatenate(([0.0], np.sort(rng.uniform(0, L, P - 1)), [L]))
            x = rng.uniform(-3 * L, 4 * L, (400, d))
            x[:20] = L * rng.integers(-3, 4, (20, d))  # multiples of L
            x[20, 0], x[21, 0] = -5e-324, -1e-17  # below 0 by a denormal, and by a hair
            x[22:22 + P + 1, 0] = bounds  # on the bounds
            want = SlabDomain(MPI.COMM_SELF, L, [0.0, L]).fold(x)
            # SlabDomain.owner(folded=True) on P slabs (a domain of P ranks needs P ranks)
            want_owner = np.clip(np.searchsorted(bounds, want[:, 0], side="right") - 1, 0, P - 1)
            got, owner = rowops.fold_owner(x, L, bounds)
            assert np.array_equal(got.view(np.int64), want.view(np.int64))
            assert 0.0 <= got.min() and got.max() <= L
            np.testing.assert_array_equal(owner, want_owner)
            again = rowops.fold_owner(want, L, bounds, folded=True)[1]
            np.testing.assert_array_equal(again, want_owner)
            assert rowops.fold_owner(x, L)[1] is None
    finally:
        monkeypatch.delenv("PARJAM_KERNELS", raising=False)
        kernels.reset()


def test_merge_rows_is_a_concatenation_taken():
    """rowops.merge_rows (one compiled pass, as a migration merges the rows a rank keeps with
    those handed to it) against numpy's concatenate + take, bit for bit, for positions (n, 3),
    ids (int64) and diameters; with no arrivals, and with no row kept."""
    rng = np.random.default_rng(2)
    for n_old, n_new in ((50, 7), (40, 0), (0, 9)):
        for shape, dtype in (((3,), np.float64), ((), np.int64), ((), np.float64)):
            old = rng.normal(size=(n_old,) + shape).astype(dtype)
            fresh = rng.normal(size=(n_new,) + shape).astype(dtype)
            if dtype == np.int64:
                old, fresh = rng.integers(-2**62, 2**62, n_old), rng.integers(0, 99, n_new)
            rows = rng.permutation(n_old + n_new)[:max(1, (n_old + n_new) * 3 // 4)]
            want = np.concatenate([old, fresh]).take(rows, axis=0)
            got = rowops.merge_rows(rows, old, fresh)
            assert got.dtype == want.dtype and got.shape == want.shape
            assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("d, poly", [(3, "mono"), (2, "bi")])
def test_every_rebuild_lists_every_pair_within_its_reach(d, poly):
    """The rebuilds that search the last ghost plan's rows again (no hand-over, no halo
    exchange: SlabEngine._search) and those that plan anew both list, over all ranks, exactly
    the pairs closer than their own reach (d_i + d_j) / 2 + skin at the rebuild's positions (a
    k-d tree over all particles: none missing, none beyond it), through many rebuilds of a
    damped run from a random start in which particles cross slab and periodic boundaries: two
    halves of a start stream along axis 0 at +-0.5 through each other at the plane x_0 = L / 2
    (on two ranks a slab boundary) and apart at x_0 = 0, ballistically (eps = 0: no forces), so
    that the drift since a plan is the bound the engine keeps (a bound twice as loose fails
    here on three ranks)."""
    from scipy.spatial import cKDTree

    pack = random_packing(d, 1500, 0.86 if d == 2 else 0.66, 2.0, poly, 1.4,
                          np.random.default_rng(6))
    v = np.zeros_like(pack.pos)
    v[:, 0] = np.where(np.mod(pack.pos[:, 0], pack.L) < 0.5 * pack.L, 0.5, -0.5)
    x, ids, diam, vv = strided(pack, v)
    eng = SlabEngine(COMM, pack.L, pack.alpha, 0.0, 0.2 * pack.diam.min(), x, ids, diam, vv)
    several = COMM.size > 1
    assert eng.margin > 0 if several else eng.margin == 0
    kinds = []

    def check_list():
        pos = gathered(eng, eng.xu)
        x = np.mod(pos, pack.L)
        x = np.minimum(x, np.nextafter(pack.L, 0))
        tree = cKDTree(x, boxsize=pack.L)
        near = tree.query_pairs(eng.cut * (1 + 1e-9), output_type="ndarray")
        r = x[near[:, 1]] - x[near[:, 0]]
        r = np.linalg.norm(r - pack.L * np.rint(r / pack.L), axis=1)
        reach = 0.5 * (pack.diam[near[:, 0]] + pack.diam[near[:, 1]]) + eng.skin
        inner = {tuple(p) for p in near[r < reach * (1 - 1e-9)]}
        outer = {tuple(p) for p in near[r < reach * (1 + 1e-9)]}
        a, b = eng.row_ids[eng.pi], eng.row_ids[eng.pj]
        assert np.all(a < b)  # the global (i, j) order's lower end first
        mine = set(zip(a.tolist(), b.tolist()))
        listed = set().union(*COMM.allgather(mine))
        assert inner <= listed <= outer
        assert len(inner) > pack.n

    s = eng.start()
    check_list()
    seen = (eng.n_rebuilds, eng.n_plans)
    for _ in range(400):
        s = eng.step(0.05, False, 1.0, 0.0, s)
        if eng.n_rebuilds != seen[0]:
            kinds.append(eng.n_plans != seen[1])
            seen = (eng.n_rebuilds, eng.n_plans)
            check_list()
    assert len(kinds) > 8
    if several:  # both kinds of rebuild were checked
        assert any(kinds) and not all(kinds)
    else:
        assert all(kinds)


@pytest.mark.parametrize("numpy_kernels", [False, True])
def test_search_points_are_the_plans_points_moved_and_folded(monkeypatch, numpy_kernels):
    """rowops.search_points (compiled, and its numpy fallback): the rows' positions plus the
    plan's offsets, folded into [0, L) along every axis but the first as fold_owner folds (the
    same bits), axis 0 left open; the reference rows copied alongside."""
    if numpy_kernels:
        monkeypatch.setenv("PARJAM_KERNELS", "numpy")
    kernels.reset()
    try:
        rng = np.random.default_rng(9)
        for d, L in ((3, 7.3), (2, 5.0)):
            pos = rng.uniform(-2 * L, 3 * L, (300, d))
            src = rng.integers(0, 300, 500)
            offset = rng.uniform(-L, L, (500, d))
            offset[:10] = -pos[src[:10]]  # lands on 0
            offset[10:20] = L * rng.integers(-2, 3, (10, d)) - pos[src[10:20]]  # on multiples
            ref = np.empty((120, d))
            got = rowops.search_points(src, pos, offset, L, ref=ref)
            moved = pos[src] + offset
            want = moved.copy()
            want[:, 1:] = rowops.fold_owner(moved[:, 1:], L)[0]
            assert np.array_equal(got.view(np.int64), want.view(np.int64))
            assert 0.0 <= got[:, 1:].min() and got[:, 1:].max() <= L
            np.testing.assert_array_equal(ref, pos[:120])
    finally:
        monkeypatch.delenv("PARJAM_KERNELS", raising=False)
        kernels.reset()


def test_balance_weighs_the_work_done_since_the_last_comparison(monkeypatch):
    """SlabEngine.weigh compares speeds as work per busy second, the work being the owned
    particles summed over the steps since the last comparison (a slab that changed in between
    counts with the particles it held then): over the ranks that work is N per step exactly; a
    rank r reporting (r + 1) ns per particle-step gets the share 1 / (r + 1) of the speeds, and
    the comparison starts a new window."""
    from parjam.pack import engine as engine_module

    monkeypatch.setattr(engine_module, "BALANCE_EVERY", 0)  # no comparison of real timings
    pack = random_packing(3, 900, 0.70, 2.0, "mono", 1.4, np.random.default_rng(11))
    eng = engine(pack)
    s = eng.start()
    eng.work = 0
    for _ in range(37):
        s = eng.step(0.05, False, 0.95, 0.02, s)
    if COMM.size == 1:  # one rank has nothing to balance: its step counts nothing
        assert eng.work == 0 and eng.shares is None
        return
    assert COMM.allreduce(eng.work) == 37 * pack.n
    eng.busy = (COMM.rank + 1.0) * eng.work * 1e-9
    eng.weigh()
    assert eng.work == 0 and eng.busy == 0.0
    speed = np.array(COMM.allgather(1.0 / (COMM.rank + 1.0)))
    np.testing.assert_allclose(eng.shares, speed / speed.sum(), rtol=1e-12)


def test_slab_shares_follow_the_measured_work_and_change_no_bit(monkeypatch):
    """Load balance by measured work (SlabEngine.weigh): when rank r reports r + 1 busy
    seconds for its (equal) share of particles, the next ghost plan gives the ranks particles in
    proportion to their speed, 1 / (r + 1) (to the count histogram's resolution), and the run
    goes on bitwise as with equal slabs: positions, forces and FIRE's sums."""
    from parjam.pack import engine as engine_module

    monkeypatch.setattr(engine_module, "BALANCE_EVERY", 0)  # no comparison of real timings
    pack = random_packing(3, 1200, 0.70, 2.0, "bi", 1.4, np.random.default_rng(7))
    runs = []
    for skew in (False, True):
        eng = engine(pack)
        s = eng.start()
        if skew:
            eng.busy = COMM.rank + 1.0
            eng.weigh()
        for _ in range(120):
            s = eng.step(0.05, False, 0.95, 0.02, s)
        runs.append((eng, s, gathered(eng, eng.xu), gathered(eng, eng.f)))
    (even, s0, x0, f0), (skewed, s1, x1, f1) = runs
    assert np.array_equal(x0, x1) and np.array_equal(f0, f1)
    assert (s0.power, s0.f2, s0.v2, s0.fmax) == (s1.power, s1.f2, s1.v2, s1.fmax)
    assert even.shares is None and even.n_balances == 0
    if COMM.size == 1:  # one rank has nothing to balance
        assert skewed.shares is None and skewed.n_balances == 0
        return
    speed = np.array(COMM.allgather(1.0 / (COMM.rank + 1.0)))
    want = speed / speed.sum()
    assert skewed.n_balances == 1 and skewed.n_plans > 1
    np.testing.assert_allclose(skewed.shares, want, rtol=0.05)
    got = np.array(COMM.allgather(skewed.n_own)) / pack.n
    np.testing.assert_allclose(got, want, atol=0.03)
