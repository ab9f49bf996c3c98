"""The packing protocol's per-state network and stability check on the slabs (parjam.pack.jamnet,
parjam.pack.stability) against the serial references: network.analyze's numbers, the
dense dynamical matrix of the non-rattlers and its LAPACK eigenvalues, and the serial energies
along a line.  The network's sums over contacts are exact (math.fsum of the serial terms) on
any number of ranks; the rest bit-identical on one rank, to round-off on 2 ranks (the MPI pass)
and, through one serial test, on 3."""

import math
import os

import numpy as np
import pytest
from mpi4py import MPI

from parjam.net.blocks import contact_blocks
from parjam import env
from parjam.net import network, potential
from parjam.pack import jamnet, stability
from parjam.vib import hessian
from parjam.files.h5md import read_packing
from parjam.pack.packing import Jammer
from parjam.net.system import wrap

from conftest import DATA, run_on_ranks

COMM = MPI.COMM_WORLD
WORLD = env.petsc().COMM_WORLD
PACKINGS = ["ref_d2_bi_N128_dphi1e-03.h5", "ref_d3_mono_N128_dphi1e-06.h5",
            "soft_d3_N256_m0.h5"]
ONE = COMM.Get_size() == 1


def close(got, want, rtol=1e-12, atol=0.0):
    """Bitwise on one rank, to round-off on several."""
    got, want = np.asarray(got, dtype=float), np.asarray(want, dtype=float)
    if ONE:
        return np.array_equal(got, want)
    return np.allclose(got, want, rtol=rtol, atol=atol)


def dense_active(pack):
    """Serial dense D of the non-rattlers (active numbers in particle order), their ids."""
    net = network.analyze(pack)
    c = network.active_contacts(net)
    blocks = contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    return (hessian.dense_hessian(net.n_active, pack.d, c.i, c.j, blocks),
            np.flatnonzero(~net.rattler))


@pytest.mark.parametrize("name", PACKINGS)
def test_network_numbers_equal_the_serial_ones(name):
    pack = read_packing(os.path.join(DATA, name))
    ref = network.analyze(pack)
    net = jamnet.from_packing(COMM, pack)
    assert (net.n, net.n_active, net.n_contacts, net.excess) == \
        (ref.n, ref.n_active, ref.n_contacts, ref.excess)
    k = np.mean(potential.d2V(ref.contacts.r, ref.contacts.sigma, pack.alpha, pack.eps))
    for got, want in ((net.energy, ref.energy), (net.pressure, ref.pressure),
                      (net.stress, ref.stress), (net.mean_force, ref.mean_force),
                      (net.mean_stiffness, k)):
        assert np.allclose(got, want, rtol=1e-12, atol=0.0), (got, want)
    # the sums over contacts are exact: math.fsum of the serial per-contact terms, bitwise, on
    # any number of ranks
    a, c = ref.all_contacts, ref.contacts
    w = -potential.dV(a.r, a.sigma, pack.alpha, pack.eps) / a.r
    stress = [[math.fsum(w * a.rij[:, i] * a.rij[:, j]) for j in range(pack.d)]
              for i in range(pack.d)]
    nc = len(c.r)
    exact = {"energy": math.fsum(potential.energy(a.r, a.sigma, pack.alpha, pack.eps)),
             "stress": np.array(stress) / pack.L ** pack.d,
             "mean_force": math.fsum(np.abs(potential.dV(c.r, c.sigma, pack.alpha,
                                                         pack.eps))) / nc,
             "mean_stiffness": math.fsum(potential.d2V(c.r, c.sigma, pack.alpha, pack.eps)) / nc}
    for key, want in exact.items():
        assert np.array_equal(getattr(net, key), want), key
    # the residual force is a difference of sums near zero: round-off of the largest term
    assert close(net.max_force, ref.max_force, rtol=0.0, atol=1e-15 * ref.mean_force + 1e-30)
    # rattlers and the owned active rows: a partition of the particles, in id order per rank
    rattlers = np.concatenate(COMM.allgather(net.state.ids[net.rattler]))
    assert np.array_equal(np.sort(rattlers), np.flatnonzero(ref.rattler))
    assert COMM.allreduce(net.active.hi - net.active.lo) == ref.n_active


@pytest.mark.parametrize("name", PACKINGS[:2])
def test_distributed_hessian_is_the_dense_one(name):
    """The matrix assembled from the half-edges (active numbers rank by rank) equals the dense
    serial D once permuted to particle order; its norm is the serial bound, bitwise on 1 rank."""
    pack = read_packing(os.path.join(DATA, name))
    net = jamnet.from_packing(COMM, pack)
    H = stability.active_hessian(net)
    A = H.matrix(WORLD)
    lo, hi = A.getOwnershipRange()
    rows = A.getValues(range(lo, hi), range(H.n * H.d))
    A.destroy()
    D = np.concatenate(COMM.allgather(rows))
    ids = np.concatenate(COMM.allgather(net.active.ids))  # active number -> particle id
    Dref, active = dense_active(pack)
    pos = np.searchsorted(active, ids)  # active number -> serial active number
    perm = (pos[:, None] * H.d + np.arange(H.d)).ravel()
    assert np.allclose(D, Dref[np.ix_(perm, perm)], rtol=1e-13, atol=1e-13 * abs(Dref).max())
    blocks = abs(Dref).reshape(H.n, H.d, H.n, H.d).sum(axis=(2, 3))
    assert H.norm >= np.abs(Dref).sum(axis=1).max() * (1 - 1e-12)
    assert H.norm <= 2.0 * blocks.sum(axis=1).max() * (1 + 1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_block_row_norms_are_each_blocks_infinity_norm(d):
    """The norm bound's per-block ||K||_inf, a row of blocks at a time, has the bits of the
    whole-array expression, NaN, signed zeros and magnitudes over 600 decades included."""
    rng = np.random.default_rng(d)
    b = rng.standard_normal((5003, d, d)) * 10.0 ** rng.integers(-300, 300, (5003, d, d))
    b[5, 1, 1], b[7] = np.nan, -0.0
    want = np.abs(b).sum(axis=2).max(axis=1)
    assert np.array_equal(stability.block_row_norms(b), want, equal_nan=True)
    assert stability.block_row_norms(b[:0]).shape == (0,)


def test_curvature_counts_equal_lapack():
    """count_below at thresholds between the dense eigenvalues counts them exactly, on any
    number of ranks (MUMPS inertia of the distributed D - sigma I)."""
    pack = read_packing(os.path.join(DATA, PACKINGS[1]))
    net = jamnet.from_packing(COMM, pack)
    H = stability.active_hessian(net)
    lam = np.linalg.eigvalsh(dense_active(pack)[0])
    for k in (5, 40, 200):
        sigma = 0.5 * (lam[k - 1] + lam[k])
        assert stability.count_below(WORLD, H, sigma) == k
    cur = stability.check(WORLD, net)
    assert cur.stable and cur.n_negative == 0 and cur.excess == net.excess


def test_softest_direction_is_the_dense_mode():
    pack = read_packing(os.path.join(DATA, PACKINGS[1]))
    net = jamnet.from_packing(COMM, pack)
    cur = stability.check(WORLD, net)
    direction, lam = stability.softest_direction(WORLD, net, cur)
    D, active = dense_active(pack)
    w, v = np.linalg.eigh(D)
    k = pack.d  # the d translations are the lowest (zero) eigenvalues
    assert lam == pytest.approx(w[k], rel=1e-7)
    full = np.zeros((pack.n, pack.d))
    for ids, rows in COMM.allgather((net.state.ids, direction)):
        full[ids] = rows
    want = np.zeros((pack.n, pack.d))
    want[active] = v[:, k].reshape(-1, pack.d)
    want /= np.sqrt(np.einsum("ij,ij->i", want, want)).max()
    sign = np.sign(np.vdot(full, want))
    assert np.abs(sign * full - want).max() < 1e-5


def serial_energy(pack, pos):
    c = network.find_contacts(type(pack)(pos, pack.diam, pack.L, pack.alpha, pack.eps))
    return math.fsum(potential.energy(c.r, c.sigma, pack.alpha, pack.eps)), \
        set(zip(c.i.tolist(), c.j.tolist()))


def test_line_trials_equal_the_serial_energies():
    """The escape search's energies and new-contact test along a direction, on the slabs,
    against the serial find_contacts at the moved positions: the energy is math.fsum of the
    serial contact energies, bitwise on any number of ranks."""
    pack = read_packing(os.path.join(DATA, PACKINGS[0]))
    net = jamnet.from_packing(COMM, pack)
    rng = np.random.default_rng(5)
    full = rng.standard_normal((pack.n, pack.d))
    full /= np.sqrt(np.einsum("ij,ij->i", full, full)).max()
    direction = full[net.state.ids]
    trials = stability.LineTrials(net.state, direction, pack.alpha, pack.eps)
    e0, base = serial_energy(pack, pack.pos)
    for t in (0.0, 1e-9, -3e-4, 2e-2):
        e, pairs = serial_energy(pack, wrap(pack.pos + t * full, pack.L))
        assert trials.energy(t) == e
        assert trials.new_contact(t) == bool(pairs - base)
        rows = stability.moved(net.state, direction, t)
        assert np.array_equal(rows, wrap(pack.pos + t * full, pack.L)[net.state.ids])


def test_jammer_network_from_its_block_rows():
    """The Jammer's per-state network comes from the force field's block rows (no gather) and
    equals the serial analysis; set_rows hands slab rows back to the block rows exactly."""
    pack = read_packing(os.path.join(DATA, PACKINGS[2]))
    jam = Jammer(WORLD, pack)
    try:
        net = jam.network()
        ref = network.analyze(pack)
        assert net.n_active == ref.n_active and net.n_contacts == ref.n_contacts
        assert np.isclose(net.pressure, ref.pressure, rtol=1e-12, atol=0.0)
        assert np.isclose(net.energy, ref.energy, rtol=1e-12, atol=0.0)
        ff = jam.ff
        shifted = wrap(pack.pos + 1e-3, pack.L)
        ff.set_rows(net.state.ids, shifted[net.state.ids])
        assert np.array_equal(ff.local(ff.x), shifted[ff.lo:ff.hi])
    finally:
        jam.destroy()


@pytest.mark.serial
def test_the_same_on_three_ranks():
    res = run_on_ranks("test_jamnet.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
