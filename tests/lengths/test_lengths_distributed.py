"""``parjam lengths`` on the distributed active network (parjam.lengths.sites, .lstar and the
distributed structure factor): the same cube counts and S(k) on 1, 2 and 3 ranks, and no rank
holding all N rows.  Runs serially and under ``mpirun -n 2``; one serial test reruns the file
on 3 ranks (a middle rank with neighbours on both sides)."""

import os

import numpy as np
import pytest
from mpi4py import MPI

from conftest import DATA, run_on_ranks
from parjam import env, lengths
from parjam.files import h5md, rowio
from parjam.net import active, network
from parjam.vib import structure
from parjam.lengths import cubes, sites
from parjam.lengths.lstar import cube_corners, gather_cube

COMM = MPI.COMM_WORLD
SELF = env.petsc().COMM_SELF
FIELDS = ("ell", "n", "q", "nc_in", "n_core", "nc_core", "trivial", "pieces", "null",
          "extended")


def path(name):
    return os.path.join(DATA, name)


@pytest.mark.parametrize("name", ["lengths_d2_N1024_dphi1e-01.h5", "soft_d3_N512_m0.h5"])
def test_sites_hold_only_their_rows(name):
    """Each rank reads its block of rows, owns about N/P particles after routing (the slabs are
    balanced to 1/64 of a slab), the owned non-rattlers add up to N', and their positions are
    the file's (wrapped), row for row."""
    rows = rowio.read_rows(COMM, path(name))
    s = sites.from_rows(COMM, rows)
    n, size = rows.n, COMM.Get_size()
    assert len(rows.pos) == active.row_block(n, COMM)[1] - active.row_block(n, COMM)[0]
    assert COMM.allreduce(len(s.net.owned_ids)) == n
    assert len(s.net.owned_ids) <= 1.2 * n / size + 2
    assert len(s.pos) == s.net.hi - s.net.lo
    assert COMM.allreduce(len(s.pos)) == s.net.n_active
    pack = h5md.read_packing(path(name))  # the serial reference (small file)
    np.testing.assert_array_equal(s.pos, np.mod(pack.pos[s.net.ids], pack.L))
    assert s.mean_diameter == pytest.approx(pack.diam.mean(), rel=1e-14)


def test_gathered_cubes_are_the_serial_cubes():
    """Every cube brought to its rank holds exactly the non-rattlers inside it (the serial
    network's), their internal contacts and the contacts leaving it."""
    pack = h5md.read_packing(path("lengths_d2_N1024_dphi1e-01.h5"))
    s = sites.from_packing(COMM, pack)
    net = network.analyze(pack)
    act = ~net.rattler
    pos = np.mod(pack.pos[act], pack.L)
    c = network.active_contacts(net)
    corners = cube_corners(3, [4.0, 9.0, pack.L], 2, 2, pack.L)
    for e, ell in enumerate((4.0, 9.0, pack.L)):
        for k in range(2):
            x0 = corners[e, k]
            dest = (2 * e + k) % COMM.Get_size()
            got = gather_cube(COMM, s, x0, ell, dest)
            assert (got is not None) == (COMM.Get_rank() == dest)
            if got is None:
                continue
            inside = cubes.cube_members(pos, pack.L, x0, ell)
            both = inside[c.i] & inside[c.j]
            ref = c.subset(both)
            local = np.cumsum(inside) - 1
            p, internal, leaving = got
            np.testing.assert_array_equal(p, pos[inside])
            np.testing.assert_array_equal(internal.i, local[ref.i])
            np.testing.assert_array_equal(internal.j, local[ref.j])
            np.testing.assert_array_equal(internal.rij, ref.rij)
            assert leaving == int(np.sum(inside[c.i] ^ inside[c.j]))


@pytest.mark.parametrize("name,ells", [("lengths_d2_N1024_dphi1e-03.h5", (3.0, 8.0, 16.0)),
                                       ("soft_d3_N512_m0.h5", (2.5, 4.0, 7.0))])
def test_cube_counts_the_same_on_every_rank_count(world, name, ells):
    """The table and every cube's counts on all ranks equal those on one rank (COMM_SELF),
    exactly: the same corners from the seed, the same members in the same order."""
    pack = h5md.read_packing(path(name))
    a = lengths.lstar(world, pack, ells, samples=3, seed=5)
    b = lengths.lstar(SELF, pack, ells, samples=3, seed=5)
    assert len(a.counts) == 9
    for x, y in zip(a.counts, b.counts):
        assert [getattr(x, f) for f in FIELDS] == [getattr(y, f) for f in FIELDS]
    np.testing.assert_array_equal(a.table(), b.table())
    assert a.estimate == pytest.approx(b.estimate, rel=1e-13)
    assert np.isnan(a.measured) == np.isnan(b.measured)
    assert a.measured == b.measured or np.isnan(a.measured)


def test_structure_factor_summed_over_owned_rows():
    """structure.compute over rows split between the ranks (any split) equals the serial sum,
    to round-off."""
    rng = np.random.default_rng(4)
    n, m, L = 40, 6, 7.0
    pos, vec = rng.uniform(0, L, (n, 3)), rng.normal(size=(m, n, 3))
    omega = np.sort(rng.uniform(0.1, 2.0, m))
    ref = structure.compute(vec, omega, pos, L, 2.5)
    mine = np.arange(COMM.Get_rank(), n, COMM.Get_size())
    got = structure.compute(vec[:, mine], omega, pos[mine], L, 2.5, comm=COMM)
    np.testing.assert_allclose(got.weight_L, ref.weight_L, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got.weight_T, ref.weight_T, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(got.m2, ref.m2)


def test_structure_the_same_on_every_rank_count(world):
    """``lengths.compute(..., ("structure",))``: eigenvector rows sent to their owners, F_L and
    F_T summed there; equal on all ranks and on one rank to round-off."""
    pack = h5md.read_packing(path("ref_d2_bi_N128_dphi1e-03.h5"))
    a = lengths.compute(world, pack, ("omega", "structure"), k_max=2.5)
    b = lengths.compute(SELF, pack, ("omega", "structure"), k_max=2.5)
    np.testing.assert_allclose(a.structure.omega, b.structure.omega, rtol=1e-10)
    np.testing.assert_allclose(a.structure.weight_L, b.structure.weight_L, atol=1e-10)
    np.testing.assert_allclose(a.structure.weight_T, b.structure.weight_T, atol=1e-10)
    assert a.structure_fit["c_T_fit"] == pytest.approx(b.structure_fit["c_T_fit"], rel=1e-8)
    assert a.rho == pytest.approx(b.rho, rel=1e-15)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """The partition cases two ranks cannot make: a middle rank, cubes of three owners."""
    res = run_on_ranks("test_lengths_distributed.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
