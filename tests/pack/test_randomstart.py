"""The random start by row blocks (parjam.pack.randomstart) against the serial start it replaces: the
stream's draws of a rank's rows, numpy's sum across ranks (parjam.net.exactsum), the rows of every
rank gathered (here, in the test only) to the serial configuration bitwise (positions, diameters,
species, numbering, box, phi) in 2D and 3D, mono/bi/poly, n not divisible by the ranks, fewer
particles than ranks and a box of a single cell; the Jammer started from its rows against the
Jammer of the whole packing; a whole ``parjam pack`` of one member shared by 2 ranks against the
same run on 1 rank.  The 2-rank pass runs every MPI test; 3 ranks: the serial test
``test_the_same_on_three_ranks`` reruns this file under $PARJAM_MPIRUN -n 3."""

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam.net import exactsum
from parjam.pack import randomstart
from parjam.net.active import row_block
from parjam.testing.h5compare import assert_same_member
from parjam.pack.packing import Jammer
from parjam.net.system import sphere_volume

from conftest import ROOT, run_on_ranks, subprocess_env

COMM = MPI.COMM_WORLD


def serial_start(d, n, phi, dispersity, ratio, rng):
    """The serial random start as parjam made it before the row blocks: every
    draw of the stream at once, then a global stable argsort of the cell keys."""
    if dispersity == "poly":
        diam, species = 1.0 + (ratio - 1.0) * rng.random(n), np.zeros(n, dtype=np.int32)
    elif dispersity == "bi":
        species = (np.arange(n) >= n // 2).astype(np.int32)
        diam = np.where(species == 1, ratio, 1.0)
    else:
        diam, species = np.ones(n), np.zeros(n, dtype=np.int32)
    L = float((sphere_volume(diam, d).sum() / phi) ** (1.0 / d))
    pos = rng.uniform(0.0, L, size=(n, d))
    pos[pos >= L] = 0.0
    m = max(1, int(L // (2.0 * diam.max())))
    idx = np.minimum((pos / L * m).astype(np.int64), m - 1)
    key = np.zeros(n, dtype=np.int64)
    for k in range(d):
        key = key * m + idx[:, k]
    order = np.argsort(key, kind="stable")
    return pos[order], diam[order], species[order], L, m, order


def gathered(rows):
    return np.concatenate(COMM.allgather(np.asarray(rows)))


def test_stream_rows_are_the_serial_draws():
    """One 64-bit word per double of ``random`` and of ``uniform`` (also of an (n, d) uniform,
    row by row): a copy advanced to a row's draw index draws what the serial stream draws there,
    and the stream is left where the serial draws leave it."""
    n, d = 1001, 3
    serial = randomstart.member_rng(4, 2)
    diam = serial.random(n)
    pos = serial.uniform(0.0, 7.5, size=(n, d))
    fresh = randomstart.member_rng(4, 2)
    for a, b in ((0, 1), (0, n), (333, 334), (500, 1001), (1000, 1001)):
        np.testing.assert_array_equal(randomstart.stream_at(fresh, a).random(b - a), diam[a:b])
        rows = randomstart.stream_at(fresh, n + a * d).uniform(0.0, 7.5, size=(b - a, d))
        np.testing.assert_array_equal(rows, pos[a:b])
        np.testing.assert_array_equal(randomstart.position_rows(a, b, n, d, 7.5, "poly", fresh),
                                      np.where(pos[a:b] >= 7.5, 0.0, pos[a:b]))
    assert fresh.bit_generator.state == randomstart.member_rng(4, 2).bit_generator.state
    randomstart.start_rows(None, d, n, 0.5, 2.0, "poly", 1.4, fresh)
    assert fresh.bit_generator.state == serial.bit_generator.state


@pytest.mark.parametrize("n", [1, 2, 7, 8, 127, 128, 129, 300, 1000, 8192, 8193, 3 * 8192 + 5,
                               100003])
def test_the_sum_across_ranks_is_numpys_sum(n):
    """exactsum.total over the ranks' blocks (PETSc's split, and a random uneven one with empty
    blocks) is np.sum of the whole array bitwise (values over 9 decades, so that another order
    of the additions shows); in process, the pairwise tree of one chunk from 1 to 7 blocks."""
    rng = np.random.default_rng(n)
    x = 10.0 ** rng.uniform(-3, 6, n)
    want = np.sum(x)
    lo, hi = row_block(n, COMM)
    assert exactsum.total(COMM, x[lo:hi], lo, n) == want
    cuts = np.sort(np.concatenate(([0, n], rng.integers(0, n + 1, COMM.size - 1))))
    a, b = cuts[COMM.rank], cuts[COMM.rank + 1]
    assert exactsum.total(COMM, x[a:b], a, n) == want
    e0 = min(n, exactsum.chunk_length())
    for parts in range(1, 8):
        cuts = np.sort(np.concatenate(([0, e0], rng.integers(0, e0 + 1, parts - 1))))
        local = [exactsum.local_nodes(x[a:b], a, 0, e0) for a, b in zip(cuts[:-1], cuts[1:])]
        got = exactsum.combine([s for s, _ in local], [p for _, p in local], 0, e0)
        assert got == np.sum(x[:e0])


CASES = [(d, disp, n, phi) for d in (2, 3) for disp in ("mono", "bi", "poly")
         for n, phi in ((5, 0.6), (101, 0.05), (1000, 0.5))] + [(3, "poly", 20000, 0.3)]


@pytest.mark.parametrize("d,dispersity,n,phi", CASES)
def test_rows_gather_to_the_serial_start(d, dispersity, n, phi):
    """Every rank's rows, gathered, are the serial start bitwise: same numbering (the positions
    are distinct, so equal positions mean the same permutation), diameters, species, box and
    phi; each rank holds its PETSc block of ids only."""
    pos, diam, species, L, m, _ = serial_start(d, n, phi, dispersity, 1.4,
                                               randomstart.member_rng(n, d))
    rows = randomstart.start_rows(COMM, d, n, phi, 2.0, dispersity, 1.4,
                                  randomstart.member_rng(n, d))
    lo, hi = row_block(n, COMM)
    assert (rows.lo, len(rows.x), rows.n) == (lo, hi - lo, n)
    assert rows.L == L
    assert rows.phi == float(sphere_volume(diam, d).sum() / L**d)
    np.testing.assert_array_equal(gathered(rows.x), pos)
    np.testing.assert_array_equal(gathered(rows.diam), diam)
    np.testing.assert_array_equal(gathered(rows.meta["species"]), species)
    assert rows.meta["species"].dtype == np.int32
    if n == 5:
        assert m == 1  # a box of one cell: the order is the draw order
    else:
        assert m >= 3


def test_the_serial_wrapper_is_the_serial_start():
    """random_packing (the whole configuration on one rank) is the serial start bitwise, and
    spatial_order its permutation."""
    for d, disp in ((2, "bi"), (3, "poly")):
        pos, diam, species, L, _, order = serial_start(d, 777, 0.4, disp, 1.3,
                                                       np.random.default_rng(3))
        pack = randomstart.random_packing(d, 777, 0.4, 2.5, disp, 1.3, np.random.default_rng(3))
        assert pack.L == L and pack.alpha == 2.5
        np.testing.assert_array_equal(pack.pos, pos)
        np.testing.assert_array_equal(pack.diam, diam)
        np.testing.assert_array_equal(pack.meta["species"], species)
        unordered = np.empty_like(pos)
        unordered[order] = pos
        np.testing.assert_array_equal(randomstart.spatial_order(unordered, L, 2.0 * diam.max()),
                                      order)


def test_the_bins_follow_the_order():
    """order_bins is non-decreasing in (key, draw) order, with many keys and with few."""
    for n_keys, nbins in ((1, 128), (8, 128), (27, 64), (1000, 128), (10 ** 6, 192)):
        key = np.repeat(np.arange(n_keys), 3)[:5000]
        draw = np.tile(np.array([0, 499, 999]), len(key) // 3 + 1)[:len(key)]
        bins = randomstart.order_bins(key, draw, n_keys, 1000, nbins)
        assert np.all(np.diff(bins) >= 0) and bins.min() >= 0 and bins.max() < nbins


@pytest.mark.parametrize("d,dispersity", [(2, "bi"), (3, "poly")])
def test_jammer_from_rows_is_the_jammer_of_the_packing(world, d, dispersity):
    """The Jammer started from its block rows holds what the Jammer of the whole packing holds:
    positions, diameters, species, box, phi and sphere volume bitwise."""
    args = (d, 500, 0.6, 2.0, dispersity, 1.4)
    ref = Jammer(world, randomstart.random_packing(*args, rng=randomstart.member_rng(1, 0)))
    new = Jammer(world, randomstart.start_rows(world, *args, rng=randomstart.member_rng(1, 0)))
    try:
        assert (new.n, new.d, new.L, new.sphere_volume, new.phi) == (
            ref.n, ref.d, ref.L, ref.sphere_volume, ref.phi)
        assert (new.ff.dmin, new.ff.dmax, new.ff.lo, new.ff.hi) == (
            ref.ff.dmin, ref.ff.dmax, ref.ff.lo, ref.ff.hi)
        np.testing.assert_array_equal(new.ff.x.array, ref.ff.x.array)
        np.testing.assert_array_equal(new.ff.diam_rows, ref.ff.diam_rows)
        np.testing.assert_array_equal(new.meta["species"], ref.meta["species"])
        assert new.row_meta == ref.row_meta == {"species"}
    finally:
        ref.destroy()
        new.destroy()


def run_pack(out, ranks):
    cmd = [sys.executable, "-m", "parjam", "pack", "--dim", "3", "--n", "64", "--seed", "5",
           "--dispersity", "poly", "--dphi", "1e-4", "--out", str(out), "-q"]
    if ranks > 1:
        cmd = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split() + [
            "-n", str(ranks)] + cmd
    r = subprocess.run(cmd, cwd=ROOT, env=subprocess_env(), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]


@pytest.mark.serial
def test_a_member_shared_by_two_ranks_packs_the_serial_minimum(tmp_path):
    """One member on 2 ranks (its random start by row blocks) against the same member on 1:
    the same start, so the same minima to the round-off of a shared member
    (tests/pack/test_checkpoint.py: phi_c to 1e-12, pressure 1e-5 relative, non-rattler positions
    1e-7 after the global translation); species and diameters exactly."""
    run_pack(tmp_path / "one", 1)
    run_pack(tmp_path / "two", 2)
    names = sorted(os.listdir(tmp_path / "one"))
    assert [x for x in names if x.endswith(".h5")] and names == sorted(
        os.listdir(tmp_path / "two"))
    for name in (x for x in names if x.endswith(".h5")):
        with h5py.File(tmp_path / "one" / name, "r") as fa, \
                h5py.File(tmp_path / "two" / name, "r") as fb:
            part_a, part_b = fa["particles/all"], fb["particles/all"]
            for key in ("diameter", "species"):
                np.testing.assert_array_equal(part_a[key][()], part_b[key][()])
            assert_same_member(fa, fb, name)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A middle rank, blocks of unequal length, fewer particles than ranks."""
    res = run_on_ranks("test_randomstart.py", 3, "-k", "not three and not shared")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
