"""The operators of the cut system (Wyart et al. 2005): the relaxed-spring matrix M = S^T K S
(Eq. 1 without the stress term) and the rigidity (compatibility) matrix S of Eq. 3, assembled
from the half-edges of the owned active rows [lo, hi) of the distributed active network (one
particle per block of d rows, parjam.vib.hessian), and the d translations that span their trivial
null space."""

import numpy as np

from parjam.net.blocks import contact_blocks
from parjam import env
from parjam.net import potential
from parjam.vib import hessian


def relaxed_matrix(comm, cs, contacts, fmt="aij", shift=0.0):
    """Distributed relaxed-spring matrix M = sum_c k_c n n^T (Eq. 1 without the stress term,
    = S^T K S) of the half-edges ``contacts`` (``cs.kept`` or ``cs.contacts``) over the N'
    non-rattlers; ``fmt`` "aij" (MatMult, KSP) or "sbaij" (MUMPS inertia), assembled directly;
    ``shift`` is added to the diagonal."""
    blocks = contact_blocks(contacts.rij, contacts.r, contacts.sigma, cs.alpha, cs.eps,
                                    kind="relaxed")
    return hessian.assemble(comm, cs.n, cs.d, contacts.i, contacts.j, blocks, shift=shift,
                            rows=(cs.lo, cs.hi), fmt=fmt)


def rigidity_matrix(comm, cs, contacts):
    """Distributed rigidity matrix S (Nc x dN'): row c is (dR_j - dR_i) . n_ij (Eq. 3).

    Each contact is one row, on the rank owning its lower-numbered end (the half-edges with
    i < j); the columns follow the row layout of M, so S multiplies the basis vectors directly.
    """
    PETSc = env.petsc()
    d = cs.d
    c = contacts.subset(contacts.i < contacts.j)
    nrows = len(c)
    nc = comm.tompi4py().allreduce(nrows)
    n = c.rij / c.r[:, None]
    cols = np.concatenate([c.i[:, None] * d + np.arange(d), c.j[:, None] * d + np.arange(d)],
                          axis=1)
    vals = np.concatenate([-n, n], axis=1)  # -n on particle i, +n on particle j (i < j)
    indptr = np.arange(0, 2 * d * nrows + 1, 2 * d, dtype=PETSc.IntType)
    return PETSc.Mat().createAIJ(((nrows, nc), (cs.n_local * d, cs.n * d)),
                                 csr=(indptr, cols.ravel().astype(PETSc.IntType), vals.ravel()),
                                 comm=comm)


def stiffness_scale(contacts, alpha, eps, comm=None):
    """Mean contact stiffness k = V''(r): the unit in which the thresholds are set (over the
    ranks of ``comm`` when given: half-edges count every contact twice, the mean is the same)."""
    k = potential.d2V(contacts.r, contacts.sigma, alpha, eps)
    if comm is None:
        return float(np.mean(k))
    s = comm.tompi4py().allreduce(np.array([k.sum(), len(k)], dtype=float))
    return float(s[0] / s[1])


def translations(M, d):
    """The d unit translations as Vecs in the layout of M (normalised)."""
    out = []
    n = M.getSize()[0] // d
    for a in range(d):
        v = M.createVecRight()
        lo, hi = v.getOwnershipRange()
        arr = np.zeros(hi - lo)
        arr[(np.arange(lo, hi) % d) == a] = 1.0 / np.sqrt(n)
        v.setArray(arr)
        out.append(v)
    return out


def translation_columns(M, d):
    """The d normalised translations as this rank's rows of an array (one column each)."""
    vecs = translations(M, d)
    T = np.stack([v.getArray().copy() for v in vecs], axis=1)
    for v in vecs:
        v.destroy()
    return T
