"""The distributed active network (parjam.net.active) against the serial network.analyze: the same
contacts, rattlers, N', Nc, z, pressure and forces on 1 and 2 ranks (the MPI pass) and, through
one serial test, on 3; 2D bidisperse and 3D monodisperse packings of tests/data.  The operators
assembled from its half-edges (AIJ and SBAIJ) equal the dense reference matrix, their eigenvalues
the dense LAPACK references to 1e-8, and no solver leaves options in PETSc's database."""

import os

import numpy as np
import pytest
from mpi4py import MPI

from parjam import env
from parjam.net import active
from parjam.vib import kpm, moduli, spectrum
from parjam.files.h5md import read_packing
from parjam.net.network import analyze
from parjam.testing.reference import dense_system
from parjam.vib.dense import dense_matrix

from conftest import DATA, run_on_ranks

COMM = MPI.COMM_WORLD
WORLD = env.petsc().COMM_WORLD
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


@pytest.mark.parametrize("name", PACKINGS[:2])
def test_owned_positions_are_the_wrapped_packing_positions(name):
    """``pos`` holds every owned particle's wrapped position (rows of ``owned_ids``),
    ``active_pos`` those of the active rows lo..hi-1 (particles ``ids``)."""
    pack = read_packing(os.path.join(DATA, name))
    net = active.from_packing(COMM, pack)
    wrapped = np.mod(pack.pos, pack.L)
    assert net.pos.shape == (len(net.owned_ids), pack.d)
    assert np.array_equal(net.pos, wrapped[net.owned_ids])
    assert np.array_equal(net.active_pos, wrapped[net.ids])
    assert COMM.allreduce(len(net.pos)) == pack.n


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


def keyed_product(A, system, seed=3):
    """A x for x with entry (particle p, component a) fixed by (p, a): {p: (A x)_p} over all
    ranks, comparable between numberings."""
    keys = system.ids
    x = A.createVecRight()
    kpm.fill_probe(x, seed, 0, "gaussian", keys=keys)
    y = A.createVecLeft()
    A.mult(x, y)
    rows = y.getArray().reshape(-1, system.d).copy()
    x.destroy()
    y.destroy()
    got = COMM.allgather((np.asarray(keys), rows))
    return {int(k): r for ks, rs in got for k, r in zip(ks, rs)}


@pytest.mark.parametrize("name", PACKINGS[:2])
@pytest.mark.parametrize("fmt", ["aij", "sbaij"])
def test_assembly_equals_the_dense_reference(name, fmt):
    """The matrix from half-edges (slab rows) is the dense matrix of the serial network up to
    the numbering, in either format, preallocated exactly (no mallocs)."""
    pack = read_packing(os.path.join(DATA, name))
    ref = dense_system(pack)
    new = spectrum.distributed_system(active.from_packing(COMM, pack))
    A_new = spectrum.dynamical_matrix(WORLD, new, "full", fmt=fmt)
    assert A_new.getType().endswith(fmt) and A_new.getBlockSize() == pack.d
    assert A_new.getInfo()["mallocs"] == 0
    got = keyed_product(A_new, new)
    x = env.petsc().Vec().createSeq(ref.n * ref.d, comm=env.petsc().COMM_SELF)
    kpm.fill_probe(x, 3, 0, "gaussian", keys=ref.ids)  # the same probe, keyed by particle
    H = dense_matrix(ref, "full")
    y = (H @ x.getArray()).reshape(ref.n, ref.d)
    x.destroy()
    want = {int(p): row for p, row in zip(ref.ids, y)}
    assert sorted(want) == sorted(got)
    scale = np.abs(H).sum(axis=1).max()
    assert max(np.abs(want[k] - got[k]).max() for k in want) <= 1e-13 * scale
    A_new.destroy()


@pytest.mark.parametrize("name", ["ref_d2_bi_N128_dphi1e-03", "ref_d3_mono_N128_dphi1e-06"])
def test_distributed_eigenvalues_equal_dense_lapack(name):
    """Shift-and-invert, slicing and the dense path on the distributed system against the
    stored dense LAPACK spectra (translations kept there)."""
    pack = read_packing(os.path.join(DATA, name + ".h5"))
    ref = np.load(os.path.join(DATA, name + ".spectrum.npz"))["full"]
    s = spectrum.distributed_system(active.from_packing(COMM, pack))
    d = pack.d
    spec = spectrum.compute(WORLD, s, "full", k=12, method="sinvert", vectors=True)
    assert np.all(np.abs(spec.eigenvalue / ref[d:d + 12] - 1) <= 1e-8)
    lo, hi = d + 5, d + 30
    w = (np.sqrt(0.5 * (ref[lo - 1] + ref[lo])), np.sqrt(0.5 * (ref[hi] + ref[hi + 1])))
    sl = spectrum.compute(WORLD, s, "full", window=w, method="slice")
    assert len(sl.eigenvalue) == hi - lo + 1 and sl.complete
    assert np.all(np.abs(sl.eigenvalue / ref[lo:hi + 1] - 1) <= 1e-8)
    dense = spectrum.compute(WORLD, s, "full", k=s.n_modes, method="dense", vectors=True)
    assert np.abs(dense.eigenvalue - ref[d:]).max() <= 1e-12 * dense.norm
    self_comm = env.petsc().COMM_SELF
    serial = spectrum.compute(self_comm, spectrum.system_of(self_comm, pack), "full", k=3,
                              method="dense", vectors=True)
    rows = spec.vectors  # each rank's own rows (no rank holds all N')
    assert rows.shape == (len(spec.eigenvalue), len(s.ids), d)
    whole = spectrum.vectors_on_root(WORLD, spec)
    dense_whole = spectrum.vectors_on_root(WORLD, dense)
    serial_whole = spectrum.vectors_on_root(self_comm, serial)
    if COMM.rank == 0:  # vectors in the particle order of the file, as the serial ones
        for u, v, w in zip(dense_whole[:3], serial_whole, whole):
            assert abs(abs(np.vdot(u.ravel(), v.ravel())) - 1.0) < 1e-8
            assert abs(abs(np.vdot(w.ravel(), v.ravel())) - 1.0) < 1e-8


def test_no_options_left_in_the_database():
    """Options reach the solvers only through their prefixes: none stays behind in PETSc's
    global database after the spectrum (sinvert, slice), KPM and moduli solvers ran."""
    opts = env.petsc().Options()
    before = opts.getAll()
    pack = read_packing(os.path.join(DATA, PACKINGS[0]))
    net = active.from_packing(COMM, pack)
    s = spectrum.distributed_system(net)
    spectrum.compute(WORLD, s, "full", k=4, method="sinvert")
    spectrum.compute(WORLD, s, "full", window=(0.2, 0.4), method="slice")
    kpm.compute(WORLD, s, "full", n_moments=16, n_probes=2)
    moduli.compute(comm=WORLD, net=net)
    assert opts.getAll() == before


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A partition case two ranks cannot make: a middle rank with ghosts on both sides."""
    res = run_on_ranks("test_active.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
