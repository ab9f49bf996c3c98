"""Distributed dense algebra on blocks of columns whose rows are split over the ranks (this
rank's rows of a global n x k array): reductions, Gram matrices, projections, orthonormalisation
(SVQB), Rayleigh-Ritz, and in-place rotations done in row chunks so that no second n x k array
is ever made.  Every function is collective over ``comm``.

A basis argument may be a numpy array or a :class:`parjam.softmodes.scratch.ScratchBasis` (on
disk): the functions here touch it only through row slices ``V[a:z]``, ``V.shape`` and
:func:`column_blocks`/:func:`columns_of`."""

import numpy as np

from parjam import env

ROW_CHUNK = 1024  # rows per chunk of a rotation or reduction (temporary ROW_CHUNK x k)


def allreduce(comm, x):
    from mpi4py import MPI  # start-up order: mpi4py only after PETSc (parjam.env)

    return comm.tompi4py().allreduce(x, op=MPI.SUM)


def allmax(comm, x):
    from mpi4py import MPI  # start-up order: mpi4py only after PETSc (parjam.env)

    return comm.tompi4py().allreduce(x, op=MPI.MAX)


def gram(comm, A, B=None):
    """A^T B over the distributed rows (replicated result)."""
    B = A if B is None else B
    return allreduce(comm, A.T @ B)


def column_blocks(U):
    """The columns of U in blocks: U itself for an array, the stored blocks of a scratch basis
    (read one at a time)."""
    return U.column_blocks() if hasattr(U, "column_blocks") else (U,)


def columns_of(U, c0, c1):
    """U[:, c0:c1] (a copy for a scratch basis)."""
    return U.columns(c0, c1) if hasattr(U, "columns") else U[:, c0:c1]


def self_gram(comm, V, w=None, rows=ROW_CHUNK):
    """V^T diag(w) V (w = 1 without weights) in row chunks (replicated)."""
    A = np.zeros((V.shape[1], V.shape[1]))
    for a in range(0, V.shape[0], rows):
        R = V[a:a + rows]
        A += R.T @ (R if w is None else w[a:a + rows, None] * R)
    return allreduce(comm, A)


def orthonormality_error(comm, V):
    k = V.shape[1]
    return float(np.abs(self_gram(comm, V) - np.eye(k)).max()) if k else 0.0


def random_block(lo, hi, k, seed, rows=3072, cols=64, first=0):
    """Rows lo..hi-1 and columns first..first+k-1 of a global Gaussian matrix drawn in fixed
    tiles of ``rows`` x ``cols``, so that neither the number of ranks nor the column blocks of
    the null-space method change the start (a tile needs only its own seed)."""
    out = np.empty((hi - lo, k))
    if hi <= lo or k <= 0:
        return out
    for b in range(lo // rows, (hi - 1) // rows + 1):
        a0, a1 = max(lo, b * rows), min(hi, (b + 1) * rows)
        for c in range(first // cols, (first + k - 1) // cols + 1):
            tile = np.random.default_rng([seed, b, c]).standard_normal((rows, cols))
            c0, c1 = max(first, c * cols), min(first + k, (c + 1) * cols)
            out[a0 - lo:a1 - lo, c0 - first:c1 - first] = \
                tile[a0 - b * rows:a1 - b * rows, c0 - c * cols:c1 - c * cols]
    return out


def deflated(comm, X, *bases):
    """X with the columns of the orthonormal ``bases`` (mutually orthogonal) projected out,
    twice (classical Gram-Schmidt with one re-orthogonalisation); temporaries are X-sized.  A
    basis on disk goes first, block by block, each block read once and projected out twice
    (block Gram-Schmidt: half the reads of two sweeps); the arrays follow."""
    for U in bases:
        if hasattr(U, "column_blocks"):
            for B in U.column_blocks():
                for _ in range(2):
                    X = X - B @ gram(comm, B, X)
    for _ in range(2):
        for U in bases:
            if not hasattr(U, "column_blocks") and U.shape[1]:
                X = X - U @ gram(comm, U, X)
    return X


def normalised_columns(comm, X):
    norms = np.sqrt(allreduce(comm, (X * X).sum(axis=0)))
    return X / np.maximum(norms, np.finfo(float).tiny)


def orthonormal(comm, Y, passes=2, drop=1e-13):
    """An orthonormal basis of span(Y) by SVQB (eigendecomposition of the scaled Gram matrix),
    applied twice; directions weaker than ``drop`` relative to the strongest are dropped."""
    for _ in range(passes):
        G = gram(comm, Y)
        s = 1.0 / np.sqrt(np.maximum(np.diag(G), np.finfo(float).tiny))
        lam, W = np.linalg.eigh(G * s[:, None] * s[None, :])
        keep = lam > drop * lam.max()
        Y = (Y * s) @ (W[:, keep] / np.sqrt(lam[keep]))
    return Y


def mat_apply(comm, M, X):
    """M X for local rows X (dense MatMatMult)."""
    PETSc = env.petsc()
    nloc, k = X.shape
    n = M.getSize()[0]
    B = PETSc.Mat().createDense(((nloc, n), (PETSc.DECIDE, k)), comm=comm,
                                array=np.asfortranarray(X))
    C = M.matMult(B)
    out = C.getDenseArray().copy()
    B.destroy()
    C.destroy()
    return out


def rayleigh_ritz(comm, M, Q):
    """Ritz vectors of M in span(Q) (orthonormal), ascending, and their residual norms."""
    MQ = mat_apply(comm, M, Q)
    H = gram(comm, Q, MQ)
    theta, W = np.linalg.eigh(0.5 * (H + H.T))
    V, MV = Q @ W, MQ @ W
    res = np.sqrt(allreduce(comm, ((MV - V * theta) ** 2).sum(axis=0)))
    return V, theta, res


def replicated_eigh(comm, A):
    """Eigen-decomposition of the symmetric part of the small replicated A, computed on rank 0
    and broadcast so that every rank rotates its rows identically."""
    return comm.tompi4py().bcast(np.linalg.eigh(0.5 * (A + A.T)), root=0)


def rotate_rows(V, U, rows=ROW_CHUNK):
    """V <- V U in place when U is square, else a new array; rows are done in chunks, so the
    only temporary is ``rows`` x k (no second copy of V)."""
    if U.shape[0] == U.shape[1]:
        for a in range(0, V.shape[0], rows):
            V[a:a + rows] = V[a:a + rows] @ U
        return V
    out = np.empty((V.shape[0], U.shape[1]))
    for a in range(0, V.shape[0], rows):
        out[a:a + rows] = V[a:a + rows] @ U
    return out


def row_squares(V, rows=ROW_CHUNK):
    """sum_b V_ib^2 per row (the diagonal of V V^T), in row chunks."""
    out = np.empty(V.shape[0])
    for a in range(0, V.shape[0], rows):
        out[a:a + rows] = np.einsum("ij,ij->i", V[a:a + rows], V[a:a + rows])
    return out
