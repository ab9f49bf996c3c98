"""The dynamical matrix of a packing (the paper's Eq. (1)) as a distributed PETSc MatAIJ.

For a contact ij with unit vector n = r_ij / r, the d x d block is

    K_ij = V''(r) n n^T  +  (V'(r)/r) (I - n n^T)
           stiffness (M)     stress / "transverse" term (M'), negative for repulsion

and the Hessian has -K_ij off the diagonal and sum_j K_ij on the diagonal (unit masses).
``kind`` selects the full matrix D = M + M', the relaxed-spring matrix M (Section III) or M'.

Rows are partitioned over ranks in blocks of d (one particle per block row).  Each rank
receives the contacts that touch its own rows and inserts only into those rows, so assembly
needs no off-process communication; the local CSR is built in numpy and handed to PETSc in one
call, which preallocates exactly (no mallocs, checked in the tests through MatGetInfo).
"""

import numpy as np

from parjam import env, potential

KINDS = ("full", "relaxed", "stress")


def contact_blocks(rij, r, sigma, alpha, eps=1.0, kind="full"):
    """Per-contact d x d blocks K_ij of Eq. (1) for the requested ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"unknown matrix kind {kind!r}; choose from {', '.join(KINDS)}")
    d = rij.shape[1]
    n = rij / r[:, None]
    nn = n[:, :, None] * n[:, None, :]
    blocks = np.zeros((len(r), d, d))
    if kind in ("full", "relaxed"):
        blocks += potential.d2V(r, sigma, alpha, eps)[:, None, None] * nn
    if kind in ("full", "stress"):
        t = potential.dV(r, sigma, alpha, eps) / r
        blocks += t[:, None, None] * (np.eye(d)[None] - nn)
    return blocks


def row_range(n, comm):
    """First and one-past-last particle (block row) owned by this rank: PETSc's default split."""
    PETSc = env.petsc()
    nloc, _ = PETSc.Sys.splitOwnership(n, comm=comm)
    hi = comm.tompi4py().scan(nloc)
    return hi - nloc, hi


def local_block_csr(n, lo, hi, pi, pj, blocks):
    """Block triplets of the rows [lo, hi) from contacts (pi, pj): summed, sorted by (row, col),
    with an explicit (possibly zero) diagonal block in every row."""
    d = blocks.shape[1]
    own_i = (pi >= lo) & (pi < hi)
    own_j = (pj >= lo) & (pj < hi)
    rows = np.concatenate([pi[own_i], pi[own_i], pj[own_j], pj[own_j], np.arange(lo, hi)])
    cols = np.concatenate([pi[own_i], pj[own_i], pj[own_j], pi[own_j], np.arange(lo, hi)])
    vals = np.concatenate([blocks[own_i], -blocks[own_i], blocks[own_j], -blocks[own_j],
                           np.zeros((hi - lo, d, d))])
    key = rows.astype(np.int64) * n + cols
    uniq, inverse = np.unique(key, return_inverse=True)
    summed = np.zeros((len(uniq), d, d))
    np.add.at(summed, inverse, vals)
    return uniq // n, uniq % n, summed


def scalar_csr(lo, hi, brow, bcol, bvals):
    """Expand sorted block triplets of rows [lo, hi) into a scalar CSR with global columns."""
    nb, d, _ = bvals.shape
    k = np.arange(nb)[:, None, None]
    a = np.arange(d)[None, :, None]
    c = np.arange(d)[None, None, :]
    srow = np.broadcast_to((brow[k] - lo) * d + a, (nb, d, d)).ravel()
    scol = np.broadcast_to(bcol[k] * d + c, (nb, d, d)).ravel()
    order = np.argsort(srow, kind="stable")
    counts = np.bincount(srow, minlength=(hi - lo) * d)
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(PETSC_INT())
    return indptr, scol[order].astype(PETSC_INT()), bvals.ravel()[order]


def PETSC_INT():
    return env.petsc().IntType


def local_csr(comm, n, d, pi, pj, blocks, shift=0.0):
    """Scalar CSR (indptr, global columns, values) of this rank's rows; ``shift`` is added to the
    diagonal."""
    lo, hi = row_range(n, comm)
    brow, bcol, bvals = local_block_csr(n, lo, hi, np.asarray(pi), np.asarray(pj), blocks)
    if shift:
        diag = brow == bcol
        bvals[diag] += shift * np.eye(d)
    return scalar_csr(lo, hi, brow, bcol, bvals)


def assemble(comm, n, d, pi, pj, blocks, shift=0.0):
    """Distributed MatAIJ (block size d) of n particles from contacts touching this rank's rows.

    ``pi``, ``pj`` are global particle indices of contacts with at least one owned endpoint
    (extra contacts are ignored), ``blocks`` their K_ij.  ``shift`` is added to the diagonal.
    """
    PETSc = env.petsc()
    indptr, cols, vals = local_csr(comm, n, d, pi, pj, blocks, shift)
    m = len(indptr) - 1
    A = PETSc.Mat().createAIJ(((m, n * d), (m, n * d)), bsize=d, csr=(indptr, cols, vals),
                              comm=comm)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
    return A


def dense_hessian(n, d, pi, pj, blocks):
    """Dense (n d x n d) Hessian from all contacts: the exact small-system reference."""
    H = np.zeros((n, d, n, d))
    for a, b, K in zip(pi, pj, blocks):
        H[a, :, a, :] += K
        H[b, :, b, :] += K
        H[a, :, b, :] -= K
        H[b, :, a, :] -= K
    return H.reshape(n * d, n * d)
