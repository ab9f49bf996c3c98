"""The dynamical matrix of a packing (the paper's Eq. (1)) as a distributed PETSc MatAIJ.

For a contact ij the d x d block K_ij is parjam.net.blocks' (re-exported here with its KINDS),
and the Hessian has -K_ij off the diagonal and sum_j K_ij on the diagonal (unit masses).
``kind`` selects the full matrix D = M + M', the relaxed-spring matrix M (Section III) or M'.

Rows are partitioned over ranks in blocks of d (one particle per block row).  Each rank
inserts only into its own rows, so assembly needs no off-process communication; the local CSR
is built in numpy and handed to PETSc in one call, which preallocates exactly (no mallocs,
checked in the tests through MatGetInfo).  Two ways to give the contacts:

- ``rows=(lo, hi)``: the half-edges of parjam.net.active (pi owned, in [lo, hi); every contact once
  per owned end), so a rank needs only its own particles' contacts.  ``fmt`` is the format the
  solver needs: "aij" (MatMult, KSP, GAMG) or "sbaij" (the upper triangle only: MUMPS Cholesky
  and its inertia), assembled directly, never converted;
- ``rows=None``: whole contacts (pi < pj, each once) with at least one end in PETSc's default
  row split (``row_range``), the replicated lists of small systems (packing, softmodes).
"""

import numpy as np

from parjam import env
from parjam.net.blocks import KINDS, contact_blocks  # noqa: F401 (what it assembles)


def row_range(n, comm):
    """First and one-past-last particle (block row) owned by this rank: PETSc's default split."""
    PETSc = env.petsc()
    nloc, _ = PETSc.Sys.splitOwnership(n, comm=comm)
    hi = comm.tompi4py().scan(nloc)
    return hi - nloc, hi


def half_edges_of(lo, hi, pi, pj, blocks):
    """Whole contacts (each once) -> the half-edges owned by rows [lo, hi): (i, j, K) for every
    owned end i of a contact, j its other end."""
    pi, pj = np.asarray(pi, dtype=np.int64), np.asarray(pj, dtype=np.int64)
    own_i, own_j = (pi >= lo) & (pi < hi), (pj >= lo) & (pj < hi)
    return (np.concatenate([pi[own_i], pj[own_j]]), np.concatenate([pj[own_i], pi[own_j]]),
            np.concatenate([blocks[own_i], blocks[own_j]]))


def local_block_csr(n, lo, hi, pi, pj, blocks):
    """Block triplets of the rows [lo, hi) from whole contacts (pi, pj): summed, sorted by
    (row, col), with an explicit (possibly zero) diagonal block in every row."""
    return half_edge_block_csr(n, lo, hi, *half_edges_of(lo, hi, pi, pj, blocks))


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


FORMATS = ("aij", "sbaij")


def half_edge_block_csr(n, lo, hi, pi, pj, blocks, upper=False):
    """Block triplets of the rows [lo, hi) from half-edges (pi owned): row pi gets +K on the
    diagonal and -K at column pj; summed, sorted, an explicit diagonal block in every row.
    ``upper`` keeps the blocks with column >= row only (SBAIJ)."""
    d = blocks.shape[1]
    keep = (pi >= lo) & (pi < hi)
    pi, pj, blocks = pi[keep], pj[keep], blocks[keep]
    if upper:
        up = pj > pi
        rows = np.concatenate([pi, pi[up], np.arange(lo, hi)])
        cols = np.concatenate([pi, pj[up], np.arange(lo, hi)])
        vals = np.concatenate([blocks, -blocks[up], np.zeros((hi - lo, d, d))])
    else:
        rows = np.concatenate([pi, pi, np.arange(lo, hi)])
        cols = np.concatenate([pi, pj, np.arange(lo, hi)])
        vals = np.concatenate([blocks, -blocks, np.zeros((hi - lo, d, d))])
    key = rows.astype(np.int64) * n + cols
    uniq, inverse = np.unique(key, return_inverse=True)
    summed = np.zeros((len(uniq), d, d))
    np.add.at(summed, inverse, vals)
    return uniq // n, uniq % n, summed


def assemble(comm, n, d, pi, pj, blocks, shift=0.0, rows=None, fmt="aij"):
    """Distributed MatAIJ or MatSBAIJ (block size d) of n particles; ``shift`` is added to the
    diagonal.  With ``rows=(lo, hi)`` (this rank's block rows) ``pi``, ``pj`` are half-edges,
    pi owned; without, whole contacts touching PETSc's default rows (extra ones are ignored).
    Symmetric by construction (flagged so, for the solvers)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown matrix format {fmt!r}; choose from {', '.join(FORMATS)}")
    PETSc = env.petsc()
    pi, pj = np.asarray(pi, dtype=np.int64), np.asarray(pj, dtype=np.int64)
    if rows is None:
        lo, hi = row_range(n, comm)
        pi, pj, blocks = half_edges_of(lo, hi, pi, pj, blocks)
    else:
        lo, hi = (int(r) for r in rows)
    brow, bcol, bvals = half_edge_block_csr(n, lo, hi, pi, pj, blocks, upper=fmt == "sbaij")
    if shift:
        bvals[brow == bcol] += shift * np.eye(d)
    m = (hi - lo) * d
    size = ((m, n * d), (m, n * d))
    if fmt == "aij":
        A = PETSc.Mat().createAIJ(size, bsize=d, csr=scalar_csr(lo, hi, brow, bcol, bvals),
                                  comm=comm)
    else:
        counts = np.bincount(brow - lo, minlength=hi - lo)
        indptr = np.concatenate([[0], np.cumsum(counts)]).astype(PETSC_INT())
        A = PETSc.Mat().createSBAIJ(size, bsize=d, csr=(indptr, bcol.astype(PETSC_INT()),
                                                        bvals.reshape(-1)), comm=comm)
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
