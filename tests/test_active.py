"""The distributed active network (parjam.active) against the serial network.analyze: the same
contacts, rattlers, N', Nc, z, pressure and forces on 1 and 2 ranks (the MPI pass) and, through
one serial test, on 3; 2D bidisperse and 3D monodisperse packings of tests/data."""

import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

from parjam import active
from parjam.io import read_packing
from parjam.network import analyze

from conftest import DATA, ROOT, subprocess_env

COMM = MPI.COMM_WORLD
PACKINGS = ["ref_d2_bi_N128_dphi1e-03.h5", "ref_d3_mono_N128_dphi1e-06.h5",
            "soft_d3_N256_m0.h5", "soft_d2_N256_m1.h5"]


def gathered_pairs(net):
    """Every active contact as (smaller id, larger id), from all ranks' half-edges."""
    ids = np.concatenate(COMM.allgather(net.ids))  # active number -> particle id
    i = ids[np.concatenate(COMM.allgather(net.contacts.i))]
    j = ids[np.concatenate(COMM.allgather(net.contacts.j))]
    return i, j


@pytest.mark.parametrize("name", PACKINGS)
def test_the_serial_network_on_any_ranks(name):
    pack = read_packing(os.path.join(DATA, name))
    ref = analyze(pack)
    net = active.from_packing(COMM, pack)
    got, want = net.summary(), ref.summary()
    for key in want:
        assert np.isclose(got[key], want[key], rtol=1e-12, atol=1e-16), key
    assert net.n_active == ref.n_active and net.n_contacts == ref.n_contacts
    i, j = gathered_pairs(net)
    # every contact twice (once per end), on the rank owning that end
    assert len(i) == 2 * ref.n_contacts
    one = i < j
    assert sorted(zip(i[one].tolist(), j[one].tolist())) == sorted(
        zip(ref.contacts.i.tolist(), ref.contacts.j.tolist()))
    assert sorted(zip(j[~one].tolist(), i[~one].tolist())) == sorted(
        zip(ref.contacts.i.tolist(), ref.contacts.j.tolist()))
    ratt = np.sort(np.concatenate(COMM.allgather(net.owned_ids[net.rattler])))
    assert np.array_equal(ratt, np.flatnonzero(ref.rattler))
    assert np.allclose(net.stress, ref.stress, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("name", PACKINGS[:2])
def test_rows_are_a_parallel_reindex(name):
    """Owned active rows are contiguous blocks tiling 0..N'-1; the geometry of each half-edge is
    the serial contact's (r, sigma, r_ij up to the direction)."""
    pack = read_packing(os.path.join(DATA, name))
    ref = analyze(pack)
    net = active.from_packing(COMM, pack)
    blocks = COMM.allgather(net.rows)
    assert blocks[0][0] == 0 and blocks[-1][1] == ref.n_active
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))
    assert len(net.ids) == net.hi - net.lo
    c = net.contacts
    assert np.all((c.i >= net.lo) & (c.i < net.hi))  # i always owned
    ids = np.concatenate(COMM.allgather(net.ids))
    key = {(a, b): k for k, (a, b) in enumerate(zip(ref.contacts.i, ref.contacts.j))}
    for a, b, rij, r, s in zip(ids[c.i], ids[c.j], c.rij, c.r, c.sigma):
        k = key[(min(a, b), max(a, b))]
        sign = 1.0 if a < b else -1.0
        assert np.allclose(sign * rij, ref.contacts.rij[k], rtol=0, atol=1e-14)
        assert r == pytest.approx(ref.contacts.r[k], rel=1e-14) and s == ref.contacts.sigma[k]
    assert np.allclose(np.linalg.norm(c.unit, axis=1), 1.0)


def test_unjammed_every_particle_a_rattler():
    """A dilute packing: no contacts, every particle a rattler, N' = 0 on every rank."""
    rng = np.random.default_rng(4)
    L = 20.0
    x = rng.uniform(0, L, (60, 3))
    start, stop = active.row_block(60, COMM)
    net = active.build(COMM, x[start:stop], np.full(stop - start, 0.1),
                       np.arange(start, stop), L)
    assert net.n_active == 0 and net.n_contacts == 0 and net.n_rattlers == 60
    assert net.rows == (0, 0)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A partition case two ranks cannot make: a middle rank with ghosts on both sides."""
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    res = subprocess.run(mpirun + ["-n", "3", sys.executable, "-m", "parjam.testing.mpi_pytest",
                                   "-q", "-p", "no:cacheprovider",
                                   os.path.join(ROOT, "tests", "test_active.py")],
                         cwd=ROOT, env=subprocess_env(), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
