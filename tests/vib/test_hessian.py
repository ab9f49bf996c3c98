"""The distributed dynamical matrix of Eq. (1): finite differences of the forces, symmetry, zero
row-block sums, exact preallocation, and the same matrix on 1 and 2 ranks (dense reference)."""

import numpy as np
import pytest

from parjam.net.blocks import KINDS, contact_blocks
from parjam import env
from parjam.files import h5md
from parjam.net import network
from parjam.testing.reference import dense_system
from parjam.vib import hessian, spectrum, translations
from parjam.vib.dense import dense_matrix

PETSc = env.petsc()
DATA = "tests/data"
KIND = "full"
FILES = ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"]


@pytest.fixture(scope="module", params=FILES)
def packing(request):
    pack = h5md.read_packing(f"{DATA}/{request.param}")
    return pack, network.analyze(pack)


def distributed(comm, n, d, contacts, blocks):
    """Assemble with each rank passing only the contacts touching its rows."""
    lo, hi = hessian.row_range(n, comm)
    mine = ((contacts.i >= lo) & (contacts.i < hi)) | ((contacts.j >= lo) & (contacts.j < hi))
    return hessian.assemble(comm, n, d, contacts.i[mine], contacts.j[mine], blocks[mine])


def to_dense(A):
    """The whole matrix on every rank (rows gathered from their owners)."""
    mpi = A.getComm().tompi4py()
    lo, hi = A.getOwnershipRange()
    indptr, cols, vals = A.getValuesCSR()
    local = np.zeros((hi - lo, A.getSize()[1]))
    for r in range(hi - lo):
        local[r, cols[indptr[r]:indptr[r + 1]]] = vals[indptr[r]:indptr[r + 1]]
    return np.vstack(mpi.allgather(local))


def in_particle_order(H, system, d):
    """A dense matrix in a distributed system's active numbering, permuted to ascending particle
    id (the numbering of the dense reference)."""
    ids = np.concatenate(PETSc.COMM_WORLD.tompi4py().allgather(system.ids)) \
        if len(H) != len(system.ids) * d else np.asarray(system.ids)
    dof = (np.argsort(ids)[:, None] * d + np.arange(d)).ravel()
    return H[np.ix_(dof, dof)]


def mult(A, x):
    """A x for a full numpy vector x (same on every rank), gathered back to every rank."""
    mpi = A.getComm().tompi4py()
    X, Y = A.createVecs()
    lo, hi = X.getOwnershipRange()
    X.array[:] = x[lo:hi]
    A.mult(X, Y)
    out = np.concatenate(mpi.allgather(Y.array.copy()))
    X.destroy()
    Y.destroy()
    return out


def forces(pack, pos):
    moved = pack.copy()
    moved.pos = pos
    return network.particle_forces(moved, network.find_contacts(moved)).ravel()


@pytest.mark.parametrize("alpha", [2.0, 2.5])
def test_matvec_equals_finite_difference_of_forces(packing, alpha):
    pack, _ = packing
    pack = pack.copy()
    pack.alpha = alpha  # any alpha: the Hessian of the energy wherever the packing is
    c = network.find_contacts(pack)
    A = distributed(PETSc.COMM_WORLD, pack.n, pack.d, c,
                    contact_blocks(c.rij, c.r, c.sigma, alpha, pack.eps, KIND))
    rng = np.random.default_rng(3)
    for _ in range(3):
        v = rng.normal(size=pack.pos.shape)
        v /= np.linalg.norm(v)
        h = 1e-7  # far below the overlaps (~1e-3): no contact opens or closes
        fd = -(forces(pack, pack.pos + h * v) - forces(pack, pack.pos - h * v)) / (2 * h)
        hv = mult(A, v.ravel())
        assert np.linalg.norm(hv - fd) <= 1e-6 * np.linalg.norm(hv)
    A.destroy()


@pytest.mark.parametrize("kind", KINDS)
def test_symmetric_zero_row_sums_no_mallocs(packing, kind):
    pack, net = packing
    system = spectrum.system_of(PETSc.COMM_WORLD, pack)
    A = spectrum.dynamical_matrix(PETSc.COMM_WORLD, system, kind)
    info = A.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)
    assert info["mallocs"] == 0
    H = to_dense(A)
    scale = np.abs(H).max()
    assert np.abs(H - H.T).max() <= 1e-14 * scale
    row_block_sums = H.reshape(system.n, system.d, system.n, system.d).sum(axis=2)
    assert np.abs(row_block_sums).max() <= 1e-13 * scale
    for t in translations.vectors(A, system.d):  # the same statement as D t = 0
        y = t.duplicate()
        A.mult(t, y)
        assert y.norm() <= 1e-13 * scale
        y.destroy()
        t.destroy()
    A.destroy()


def test_full_is_relaxed_plus_stress_and_matches_dense(packing):
    """Same matrix on any number of ranks: equal to the dense reference built from all
    contacts by one loop; D = M + M'."""
    pack, net = packing
    system = spectrum.system_of(PETSc.COMM_WORLD, pack)
    reference = dense_system(pack, net)
    dense = {}
    for kind in KINDS:
        A = spectrum.dynamical_matrix(PETSc.COMM_WORLD, system, kind)
        dense[kind] = in_particle_order(to_dense(A), system, pack.d)
        A.destroy()
        ref = dense_matrix(reference, kind)
        assert np.abs(dense[kind] - ref).max() <= 1e-14 * np.abs(ref).max()
    assert np.allclose(dense["full"], dense["relaxed"] + dense["stress"], rtol=0, atol=1e-14)
    # the stress term is negative for repulsive contacts: v^T M' v <= 0 for every v
    assert np.linalg.eigvalsh(dense["stress"]).max() <= 1e-14 * np.abs(dense["full"]).max()


def test_one_rank_equals_two_ranks(packing):
    pack, net = packing
    one = spectrum.system_of(PETSc.COMM_SELF, pack)
    world = spectrum.system_of(PETSc.COMM_WORLD, pack)
    A1 = spectrum.dynamical_matrix(PETSc.COMM_SELF, one, "full")
    Aw = spectrum.dynamical_matrix(PETSc.COMM_WORLD, world, "full")
    H1 = in_particle_order(to_dense(A1), one, pack.d)
    Hw = in_particle_order(to_dense(Aw), world, pack.d)
    assert np.abs(H1 - Hw).max() <= 1e-15 * np.abs(H1).max()
    A1.destroy()
    Aw.destroy()


def test_shift_adds_to_the_diagonal(packing):
    pack, net = packing
    c = net.contacts
    system = dense_system(pack, net)  # whole contacts, each once: the pair form of assemble
    blocks = system.blocks("full")
    comm = PETSc.COMM_WORLD
    lo, hi = hessian.row_range(system.n, comm)
    A = hessian.assemble(comm, system.n, system.d, system.i, system.j, blocks, shift=0.25)
    H = to_dense(A)
    ref = hessian.dense_hessian(system.n, system.d, system.i, system.j, blocks)
    assert np.allclose(H, ref + 0.25 * np.eye(len(ref)), rtol=0, atol=1e-14)
    assert len(c) == len(system.r)
    A.destroy()
