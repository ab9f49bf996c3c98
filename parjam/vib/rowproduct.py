"""The product of the dynamical matrix of Eq. (1) with a vector, the same bits on any number of
ranks: the operator of the stability check's Lanczos test (parjam.vib.lowest), so that its
verdict, its lowest Ritz value and the direction a packing leaves a saddle along do not depend
on how the particles are split.

PETSc's MatMult of a distributed AIJ matrix sums each row as two parts, the columns this rank
owns and then the others, so a row's round-off depends on the split.  Here row i of D v is

    (D v)_i = sum_j K_ij (v_i - v_j),

K_ij the contact block of Eq. (1) (parjam.vib.hessian.contact_blocks, the diagonal block being
sum_j K_ij), summed over the half-edges of row i in the order they come in: for the
parjam.pack.jamnet.ActiveEdges a particle's contacts with higher-id partners (ascending), then
those with lower-id partners (ascending) -- an order of global ids only.  Each K (v_i - v_j) is
taken component by component in a fixed order (no dot-product kernel whose blocking could vary),
and the rows are summed by numpy's bincount, which adds in order; the compiled kernel
(parjam/pack/_kernels.c, ``parjam_halfedge_product``) makes the same operations in the same
order, about as fast as PETSc's MatMult.  The partners' values come
from their owners through one PETSc scatter (a copy), set up once.
"""

import numpy as np

from parjam import env
from parjam.pack import kernels  # the compiled product lives with the packing kernels


class HalfEdgeProduct:
    """v -> D v on this rank's block rows [lo, hi) of n particles, from half-edges (pi owned,
    pj the other end, both in the rows' global numbering) and their d x d blocks K; v and the
    result are arrays of (hi - lo) * d values (see the module doc).  Collective per product;
    ``destroy`` frees its PETSc objects."""

    def __init__(self, comm, n, d, lo, hi, pi, pj, blocks):
        PETSc = env.petsc()
        self.mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
        self.n, self.d, self.lo, self.hi = int(n), int(d), int(lo), int(hi)
        self.rows = np.ascontiguousarray(pi, dtype=np.int64) - self.lo
        cols, pos = np.unique(np.asarray(pj, dtype=np.int64), return_inverse=True)
        self.pos = np.ascontiguousarray(pos, dtype=np.int64)
        self.K = np.ascontiguousarray(blocks, dtype=np.float64)
        pcomm = comm if hasattr(comm, "tompi4py") else PETSc.Comm(comm)
        m = (self.hi - self.lo) * self.d
        self.x = PETSc.Vec().createMPI((m, self.n * self.d), bsize=self.d, comm=pcomm)
        self.xc = PETSc.Vec().createSeq(len(cols) * self.d, bsize=self.d,
                                        comm=PETSc.COMM_SELF)
        where = PETSc.IS().createBlock(self.d, cols.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        try:
            self.scatter = PETSc.Scatter().create(self.x, where, self.xc, None)
        finally:
            where.destroy()

    def apply(self, v):
        """D v (a new array, v's shape)."""
        PETSc = env.petsc()
        d, m = self.d, self.hi - self.lo
        vr = np.asarray(v, dtype=np.float64).reshape(m, d)
        self.x.array[:] = vr.reshape(-1)
        self.scatter.scatter(self.x, self.xc, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        vc = self.xc.array_r.reshape(-1, d)
        out = np.empty((m, d))
        lib = kernels.library()
        if lib is not None:
            lib.parjam_halfedge_product(len(self.rows), d, m, self.rows, self.pos, self.K,
                                        np.ascontiguousarray(vr), np.ascontiguousarray(vc), out)
            return out.reshape(np.shape(v))
        dv = vr[self.rows] - vc[self.pos]  # v_i - v_j
        w = np.zeros_like(dv)
        for a in range(d):
            for b in range(d):
                w[:, a] += self.K[:, a, b] * dv[:, b]
        for a in range(d):
            out[:, a] = np.bincount(self.rows, weights=w[:, a], minlength=m)
        return out.reshape(np.shape(v))

    def destroy(self):
        for obj in (self.scatter, self.x, self.xc):
            obj.destroy()
