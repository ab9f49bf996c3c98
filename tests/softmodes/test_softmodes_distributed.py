"""Soft modes on the distributed active network (parjam.softmodes on parjam.net.active): the cut
flag of a contact computed on each of its two half-edges (one per owning rank) agrees, and the
cut is the serial one (network.analyze's contacts through cut_masks); the exact soft-mode count
d + q - 1 - (Nc - Nc_iso) on the reference packings (tests/data, copies of ../shared/data) for
several cuts; counts, extensions, f(x), trial energies and the written file are the same on 1
rank as on all ranks (2 in the MPI pass, 3 through one serial rerun: a middle rank with ghosts
on both sides)."""

import os
import tempfile

import h5py
import numpy as np
import pytest

from parjam.files import softmodes as soft_file
from parjam import env, softmodes as sm
from parjam.files import h5md
from parjam.net import network

from conftest import DATA, run_on_ranks

PETSc = env.petsc()
WORLD = PETSc.COMM_WORLD
SELF = PETSc.COMM_SELF
ISO = ["ref_d3_mono_N128_dphi1e-06.h5", "ref_d2_bi_N128_dphi1e-06.h5"]
HYPER = ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"]
CUTS = {"half": ["x=0.5"], "wrap": ["x=0"], "two axes": ["x=0.5", "y=0.25"],
        "parallel": ["x=0.2", "x=0.7"], "sub-boxes": 2}


def planes(d, cut):
    spec = CUTS[cut]
    if isinstance(spec, int):
        return sm.subdivision_planes(spec, d)
    return [sm.parse_cut(t, d) for t in spec]


def load(name):
    return h5md.read_packing(os.path.join(DATA, name))


@pytest.fixture(scope="module")
def tmp_all():
    mpi = WORLD.tompi4py()
    path = mpi.bcast(tempfile.mkdtemp(prefix="parjam-smd-") if mpi.Get_rank() == 0 else None)
    yield path
    mpi.Barrier()
    if mpi.Get_rank() == 0:
        import shutil

        shutil.rmtree(path, ignore_errors=True)


@pytest.mark.parametrize("cut", sorted(CUTS))
@pytest.mark.parametrize("name", ISO + HYPER[1:])
def test_both_half_edges_of_a_contact_agree_and_the_cut_is_the_serial_one(name, cut):
    """Each half-edge's flag comes from its own end (owned position, separation vector); the
    two ends of every contact, often on different ranks, give the same flag for every plane,
    and the cut contacts are those of the serial network cut from i < j."""
    pack = load(name)
    cs = sm.prepare(pack, planes(pack.d, cut), allow_hyperstatic=True, comm=WORLD)
    mpi = cs.comm
    ids = np.concatenate(mpi.allgather(cs.ids))  # active number -> particle id (small test)
    c = cs.contacts
    flags = np.stack(sm.half_edge_masks(cs.net, cs.planes) + [cs.is_cut], axis=1)
    a = np.concatenate(mpi.allgather(ids[c.i]))
    b = np.concatenate(mpi.allgather(ids[c.j]))
    f = np.concatenate(mpi.allgather(flags))
    pos = {(x, y): k for k, (x, y) in enumerate(zip(a.tolist(), b.tolist()))}
    back = np.array([pos[(y, x)] for x, y in zip(a.tolist(), b.tolist())])
    assert np.array_equal(f, f[back])  # (i, j) and (j, i): the same flags
    net = network.analyze(pack)
    serial = np.logical_or.reduce(sm.cut_masks(pack.pos, net.contacts, pack.L, cs.planes))
    got = {(x, y) for x, y, cut_ in zip(a.tolist(), b.tolist(), f[:, -1]) if cut_ and x < y}
    want = set(zip(net.contacts.i[serial].tolist(), net.contacts.j[serial].tolist()))
    assert got == want and cs.q == len(want)
    assert cs.per_plane == [int(m.sum()) for m in
                            sm.cut_masks(pack.pos, net.contacts, pack.L, cs.planes)]


@pytest.mark.parametrize("cut", ["half", "wrap", "parallel", "sub-boxes"])
@pytest.mark.parametrize("name", ISO + HYPER)
def test_exact_soft_mode_count(name, cut):
    """Sec. II: the MUMPS inertia count of the cut system, distributed, is dN' - rank(S) of the
    dense rigidity matrix of the kept contacts, and d + q - 1 - (Nc - Nc_iso) + s', s' the
    self-stresses no cut contact carries: s' = 0 for the isostatic packings (exactly d + q - 1)
    and for the plane x = L/2 of the reference; s' >= 0 always (a hyperstatic packing's excess
    self-stresses can all lie away from a plane)."""
    from parjam.testing import softmodes_reference as ref

    pack = load(name)
    cs = sm.prepare(pack, planes(pack.d, cut), allow_hyperstatic=True, comm=WORLD)
    assert cs.q > cs.excess
    M = sm.relaxed_matrix(WORLD, cs, cs.kept, fmt="sbaij")
    count = sm.null_count(WORLD, M, cs.scale)
    M.destroy()
    w = cs.gathered()
    assert count == ref.dense_null_space(ref.dense_rigidity(w, w.kept))[0]
    assert (cs.excess == 0) == (name in ISO)
    if name in ISO or cut == "half":
        assert count == cs.expected_general == cs.d + cs.q - 1 - cs.excess
    assert count >= cs.expected_general


def summary_numbers(cs):
    return (cs.n, cs.n_contacts, cs.q, cs.per_plane, cs.localised, cs.z_max, cs.excess)


@pytest.mark.parametrize("cut", ["two axes", "sub-boxes"])
@pytest.mark.parametrize("name", ["soft_d3_N256_m0.h5", "soft_d2_N512_m1.h5"])
def test_one_rank_and_all_ranks_give_the_same_results(name, cut):
    """Per-mode and per-bin results of the whole analysis on COMM_SELF and on all ranks: the
    cut numbers exactly, the rest to round-off."""
    pack = load(name)
    cuts = planes(pack.d, cut)
    a = sm.analyze(SELF, sm.prepare(pack, cuts, allow_hyperstatic=True, comm=SELF), e0=0.1,
                   columns=32)
    b = sm.analyze(WORLD, sm.prepare(pack, cuts, allow_hyperstatic=True, comm=WORLD), e0=0.1,
                   columns=32)
    assert summary_numbers(a.cs) == summary_numbers(b.cs)
    assert a.cs.kappa == pytest.approx(b.cs.kappa, rel=1e-14)
    assert a.cs.scale == pytest.approx(b.cs.scale, rel=1e-12)
    assert a.count == b.count == a.cs.expected_general
    assert a.q_prime == b.q_prime and a.n_below == b.n_below
    assert np.allclose(a.e, b.e, atol=1e-11)
    assert np.allclose(a.overlap, b.overlap, atol=1e-11)
    assert np.allclose(a.modulated_energy, b.modulated_energy, atol=1e-10)
    assert np.allclose(a.trial_energy, b.trial_energy, rtol=1e-8, equal_nan=True)
    assert np.array_equal(a.fractions, b.fractions)
    assert b.eq3 < 1e-12 and b.ortho < 1e-12


def test_written_file_is_the_same_on_one_rank_and_all_ranks(tmp_all):
    """The file of one rank and of all ranks: cut contacts (particle ids), localised particles,
    the tables, and the basis in packing order (compared through the projector on the soft
    space, which does not depend on the basis chosen)."""
    pack = load(ISO[0])
    cuts = planes(pack.d, "sub-boxes")
    rank = WORLD.getRank()
    one = os.path.join(tmp_all, f"self{rank}.h5")
    every = os.path.join(tmp_all, "world.h5")
    for comm, path in ((SELF, one), (WORLD, every)):
        res = sm.analyze(comm, sm.prepare(pack, cuts, comm=comm), e0=0.1, columns=64)
        soft_file.write(comm, path, res, sm.cut_pairs(res.cs), sm.localised_ids(res.cs),
                        vectors=True, block=50)
    WORLD.tompi4py().Barrier()
    net = network.analyze(pack)
    with h5py.File(one, "r") as f, h5py.File(every, "r") as g:
        a, b = f["softmodes"], g["softmodes"]
        assert np.array_equal(a["cut_contacts"][()], b["cut_contacts"][()])
        cut = a["cut_contacts"][()]
        assert np.all(cut[:, 0] < cut[:, 1]) and len(cut) == a["count"].attrs["q"]
        assert np.array_equal(a["count"].attrs["localised_particles"],
                              b["count"].attrs["localised_particles"])
        for key in ("extension", "overlap", "extended_fraction"):
            assert np.allclose(a[key][()], b[key][()], atol=1e-11)
        Ba, Bb = a["basis"][()], b["basis"][()]
    assert np.abs(Bb[:, net.rattler]).max() == 0.0
    Pa, Pb = (np.einsum("bia,bjc->iajc", B, B) for B in (Ba, Bb))
    assert np.allclose(Pa, Pb, atol=1e-10)
    # Eq. 3 in the packing's own indexing, on the contacts that were kept
    c = net.contacts
    kept = ~np.isin(c.i * pack.n + c.j, cut[:, 0] * pack.n + cut[:, 1])
    n = c.rij[kept] / c.r[kept, None]
    assert np.abs(np.einsum("mkd,kd->mk", Bb[:, c.j[kept]] - Bb[:, c.i[kept]], n)).max() < 1e-12


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A partition case two ranks cannot make: a middle rank with ghosts on both sides."""
    res = run_on_ranks("test_softmodes_distributed.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
