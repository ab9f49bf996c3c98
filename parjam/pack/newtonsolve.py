"""Newton's linear solves, (H + mu I) dx = F, made the same bits on any number of ranks.

A distributed factorisation's round-off depends on how the matrix is split over ranks (MUMPS'
tree and fronts, ScaLAPACK's root), and so do a distributed Krylov method's dot products and an
algebraic multigrid's aggregates.  Newton's step enters the positions, so each of those would
make the packing depend on the number of ranks.  Two solvers that do not:

- ``RootFactor`` (up to NEWTON_CG_DOF degrees of freedom, the Newton tail of small packings and
  the polish near jamming): every rank assembles its block rows of H + mu I from the contacts
  alone (pairs closer than sigma_ij; each row summed over its contacts in global (i, j) order,
  parjam.vib.hessian), the rows are gathered on the member's first rank and factorised there
  by one sequential MUMPS LDL^T (KSP prefix ``newton_``, exact inertia, the same gate as
  before); the right-hand side goes there and the step comes back.  Same matrix, same
  factorisation, same step on 1 or P ranks.  Its memory is that of the one-rank factorisation,
  on one rank: that bounds its size.
- ``ExactCG`` (above it): conjugate gradients with a point-block Jacobi preconditioner (the
  d x d diagonal blocks), whose products H v are summed per particle over its contacts in
  global (i, j) order and whose dot products are exact sums (parjam.net.exactsum): every
  iterate, hence the step, is the same bits on any number of ranks.  Negative curvature
  (p.Hp <= 0) ends it as an indefinite matrix, as PETSc's CG does (the saddle gate).
  ``-newton_ksp_rtol`` and ``-newton_ksp_max_it`` set its tolerance and iteration cap.

Both work on the force field's block rows (parjam.pack.forces.ForceField) and its Vecs.
"""

import numpy as np

from parjam import env
from parjam.net import exactsum
from parjam.vib import factor, hessian
from parjam.logevents import ASSEMBLY, FACTOR, event

# Above this many degrees of freedom the factorisation (on one rank) gives way to ExactCG.
# 3D N = 32768 quench at phi = 0.66 (98k dof, one rank): the Newton phase took 120 s with CG
# + GAMG against 380 s with MUMPS (21-35 s per factorisation), same minimum (docs/results/benchmarks.md).
NEWTON_CG_DOF = 60000
CG_RTOL = 1e-8  # ExactCG's relative residual (the CG + GAMG tolerance it replaces)
CG_MAX_IT = 5000


def solver_for(ff):
    """The rank-independent solver for the force field's size (kept on it between steps)."""
    return ExactCG(ff) if ff.n * ff.d > NEWTON_CG_DOF else RootFactor(ff)


def remove_translations(ff, vec):
    """Subtract the mean displacement/force per Cartesian direction (the d zero modes); the
    means are exact sums over all particles, so the result does not depend on the ranks."""
    loc = ff.local(vec)
    sums = exactsum.totals(ff.mpi, *(loc[:, a] for a in range(ff.d)))
    loc -= np.array(sums) / ff.n


class RootFactor:
    """H + mu I from every rank's contact rows, factorised on rank 0 of the force field's
    communicator by a sequential MUMPS LDL^T (see the module doc)."""

    def __init__(self, ff):
        self.mpi = ff.mpi
        self.root = self.mpi.Get_rank() == 0
        self.ksp = self.mat = self.pattern = None
        self.ksp_type = None  # the KSP's type (rank 0's, on every rank)
        self.rhs = self.sol = None
        self.counts = None  # scalar rows per rank

    def factor(self, ff, mu):
        """Factorise H + mu I at ff's positions; returns its number of negative pivots (None:
        unknown), the same on every rank (collective)."""
        with event(ASSEMBLY):
            indptr, cols, vals = ff.contact_rows(mu)
            got = self._gather_csr(indptr, cols, vals)
        with event(FACTOR):  # on rank 0; the other ranks wait for its inertia
            neg = self._factor_root(ff, *got) if self.root else None
            neg, self.ksp_type = self.mpi.bcast(
                (neg, self.ksp.getType() if self.root else None), root=0)
            return neg

    def _gather_csr(self, indptr, cols, vals):
        lengths = np.diff(indptr).astype(np.int64)
        counts = np.array(self.mpi.allgather(len(lengths)), dtype=np.int64)
        self.counts = counts
        lengths = _gatherv(self.mpi, lengths, counts)
        nnz = np.array(self.mpi.allgather(len(cols)), dtype=np.int64)
        cols = _gatherv(self.mpi, np.asarray(cols, dtype=np.int64), nnz)
        vals = _gatherv(self.mpi, np.asarray(vals, dtype=np.float64), nnz)
        if not self.root:
            return None
        return np.concatenate([[0], np.cumsum(lengths)]), cols, vals

    def _factor_root(self, ff, indptr, cols, vals):
        PETSc = env.petsc()
        IntType = PETSc.IntType
        indptr, cols = indptr.astype(IntType), cols.astype(IntType)
        same = (self.pattern is not None and np.array_equal(self.pattern[0], indptr)
                and np.array_equal(self.pattern[1], cols))
        if same:  # the same contacts: refill, and the factorisation keeps its analysis
            self.mat.setValuesCSR(indptr, cols, vals)
            self.mat.assemble()
        else:
            if self.mat is not None:
                self.mat.destroy()
            m = ff.n * ff.d
            self.mat = PETSc.Mat().createAIJ(((m, m), (m, m)), bsize=ff.d,
                                             csr=(indptr, cols, vals), comm=PETSc.COMM_SELF)
            self.mat.setOption(PETSc.Mat.Option.SYMMETRIC, True)
            self.mat.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
            self.pattern = (indptr, cols)
            if self.ksp is not None:  # a new pattern: a new analysis
                self.ksp.destroy()
                self.ksp = None
        if self.ksp is None:
            self.ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
            self.ksp.setOptionsPrefix("newton_")
            factor.direct_cholesky(self.ksp, fallback="lu")
            self.ksp.setFromOptions()
            self.rhs, self.sol = self.mat.createVecs()
        self.ksp.setOperators(self.mat)
        factor.exact_inertia(self.ksp.getPC())
        self.ksp.setUp()
        return factor.negative_pivots(self.ksp.getPC())

    def solve(self, ff, f, dx):
        """dx = (H + mu I)^-1 f on rank 0, handed back to the block rows; returns the KSP's
        converged reason (collective)."""
        d = ff.d
        b = _gatherv(self.mpi, ff.local(f).reshape(-1), self.counts)
        reason = None
        out = None
        if self.root:
            self.rhs.array[:] = b
            self.ksp.solve(self.rhs, self.sol)
            reason = int(self.ksp.getConvergedReason())
            out = np.array(self.sol.array_r)
        reason = self.mpi.bcast(reason, root=0)
        ff.local(dx)[:] = _scatterv(self.mpi, out, self.counts).reshape(-1, d)
        return reason

    def destroy(self):
        for obj in (self.ksp, self.mat, self.rhs, self.sol):
            if obj is not None:
                obj.destroy()
        self.ksp = self.mat = self.rhs = self.sol = None


class ExactCG:
    """Preconditioned conjugate gradients on H + mu I with exact dot products (module doc)."""

    def __init__(self, ff):
        self.mpi = ff.mpi
        self.ops = None

    def factor(self, ff, mu):
        """Set up H + mu I and its block-Jacobi preconditioner; no inertia (None)."""
        self.destroy()
        with event(ASSEMBLY):
            self.ops = ff.contact_operator(mu)
        return None

    def solve(self, ff, f, dx):
        """dx ~ (H + mu I)^-1 f; returns a KSP-style converged reason: 2 (rtol), -3 (iteration
        cap), -8 (indefinite: negative curvature met) (collective)."""
        PETSc = env.petsc()
        opts = PETSc.Options()
        rtol = opts.getReal("newton_ksp_rtol", CG_RTOL)
        max_it = opts.getInt("newton_ksp_max_it", CG_MAX_IT)
        apply, precondition, _ = self.ops
        b = ff.local(f).copy()
        x = np.zeros_like(b)
        r = b.copy()
        z = precondition(r)
        p = z.copy()
        rz, bb = exactsum.totals(self.mpi, r * z, b * b)
        reason = -3
        if bb == 0.0:
            reason = 2
        for _ in range(max_it if bb > 0.0 else 0):
            q = apply(p)
            pq = exactsum.fsum(self.mpi, p * q)
            if not pq > 0.0:
                reason = -8
                break
            alpha = rz / pq
            x += alpha * p
            r -= alpha * q
            z = precondition(r)
            rz_new, rr = exactsum.totals(self.mpi, r * z, r * r)
            if rr <= rtol * rtol * bb:
                reason = 2
                break
            p = z + (rz_new / rz) * p
            rz = rz_new
        ff.local(dx)[:] = x
        return reason

    ksp_type = "exact cg"

    def destroy(self):
        if self.ops is not None:
            self.ops[2]()
        self.ops = None


def _gatherv(mpi, values, counts):
    """The ranks' ``values`` (rows per rank ``counts``, in units of ``values``' first axis)
    concatenated in rank order on rank 0 (None elsewhere)."""
    values = np.ascontiguousarray(values)
    if mpi.Get_size() == 1:
        return values
    row = int(np.prod(values.shape[1:], dtype=np.int64))
    out = np.empty((int(counts.sum()),) + values.shape[1:], values.dtype) if mpi.Get_rank() == 0 \
        else None
    sizes = counts * row
    recv = [out, (sizes, np.concatenate([[0], np.cumsum(sizes)[:-1]]))] if out is not None \
        else None
    mpi.Gatherv(values.reshape(-1), recv, root=0)
    return out


def _scatterv(mpi, values, counts):
    """Rank 0's ``values`` cut into the ranks' rows ``counts`` (each rank gets its part)."""
    if mpi.Get_size() == 1:
        return np.asarray(values)
    mine = np.empty(int(counts[mpi.Get_rank()]))
    send = None
    if mpi.Get_rank() == 0:
        send = [np.ascontiguousarray(values),
                (counts, np.concatenate([[0], np.cumsum(counts)[:-1]]))]
    mpi.Scatterv(send, mine, root=0)
    return mine
