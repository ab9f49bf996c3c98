"""The operators of the cut system (Wyart et al. 2005): the relaxed-spring matrix M = S^T K S
(Eq. 1 without the stress term) and the rigidity (compatibility) matrix S of Eq. 3, assembled
over the rows of :func:`parjam.hessian.row_range` (one particle per block of d rows), and the d
translations that span their trivial null space."""

import numpy as np

from parjam import env, hessian, potential


def owned(c, lo, hi):
    """Contacts with at least one endpoint among this rank's particles [lo, hi)."""
    return ((c.i >= lo) & (c.i < hi)) | ((c.j >= lo) & (c.j < hi))


def relaxed_matrix(comm, cs, contacts):
    """Distributed relaxed-spring matrix M = sum_c k_c n n^T (Eq. 1 without the stress term,
    = S^T K S) of ``contacts`` over the n non-rattlers."""
    lo, hi = hessian.row_range(cs.n, comm)
    c = contacts.subset(owned(contacts, lo, hi))
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, cs.alpha, cs.eps, kind="relaxed")
    return hessian.assemble(comm, cs.n, cs.d, c.i, c.j, blocks)


def rigidity_matrix(comm, cs, contacts):
    """Distributed rigidity matrix S (Nc x dN'): row c is (dR_j - dR_i) . n_ij (Eq. 3).

    Contact rows are split evenly over the ranks; the columns follow the row layout of M, so S
    multiplies the basis vectors directly.
    """
    PETSc = env.petsc()
    nc, d = len(contacts), cs.d
    lo_c, hi_c = hessian.row_range(nc, comm) if nc else (0, 0)
    lo, hi = hessian.row_range(cs.n, comm)
    i, j = contacts.i[lo_c:hi_c], contacts.j[lo_c:hi_c]
    n = contacts.rij[lo_c:hi_c] / contacts.r[lo_c:hi_c, None]
    a, b = np.minimum(i, j), np.maximum(i, j)
    sign_a = np.where(a == i, -1.0, 1.0)[:, None]  # -n on particle i, +n on particle j
    cols = np.concatenate([a[:, None] * d + np.arange(d), b[:, None] * d + np.arange(d)], axis=1)
    vals = np.concatenate([sign_a * n, -sign_a * n], axis=1)
    indptr = np.arange(0, 2 * d * len(i) + 1, 2 * d, dtype=PETSc.IntType)
    S = PETSc.Mat().createAIJ(((hi_c - lo_c, nc), ((hi - lo) * d, cs.n * d)),
                              csr=(indptr, cols.ravel().astype(PETSc.IntType), vals.ravel()),
                              comm=comm)
    return S


def stiffness_scale(contacts, alpha, eps):
    """Mean contact stiffness k = V''(r): the unit in which the thresholds are set."""
    return float(np.mean(potential.d2V(contacts.r, contacts.sigma, alpha, eps)))


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
