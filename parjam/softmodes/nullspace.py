"""The null space of the cut system (Wyart et al. 2005, Sec. II: the zero modes of M = S^T K S,
Eq. 1 without the stress term, are those of the rigidity matrix S of Eq. 3) by block inverse
iteration with one MUMPS Cholesky factor of M + tau k I, in blocks of columns.

Column blocks (``columns``, ``parjam softmodes --columns``): the n_soft null vectors are found
``columns`` at a time.  Each block starts from its own columns of one fixed Gaussian matrix
(:func:`parjam.softmodes.linalg.random_block`), is kept orthogonal to the translations and to
the vectors already found, and goes through the inverse passes and a Rayleigh-Ritz step of its
own; accepted vectors are written into the one n x n_soft basis.  The working arrays are
n x columns, so a cut needs one copy of the basis plus O(n columns) instead of the ~6 n x
(n_soft + oversample) arrays of a single block.  ``columns`` >= n_soft + oversample is the
single-block (unblocked) method; the null space, and every basis-independent result (counts,
the projector, f(x)), agree to round-off (tests/softmodes/test_softmodes_columns.py).

Out of core (``store``, ``parjam softmodes --scratch DIR``): the accepted blocks are appended to
a :class:`parjam.softmodes.scratch.ScratchBasis` instead of the n x n_soft array, and the
deflation of the next blocks and the gap solve read it back one stored block at a time.
"""

import numpy as np

from parjam import env
from parjam.vib import factor
from parjam.errors import ParjamError
from parjam.softmodes.basis import BASIS_METHODS, COLUMNS_DEFAULT, NullBasis
from parjam.softmodes.krylov import null_basis_krylov
from parjam.softmodes.linalg import (allreduce, column_blocks, deflated, normalised_columns, orthonormal,
                                     random_block, rayleigh_ritz)
from parjam.softmodes.operators import translation_columns


def null_basis(comm, M, d, n_soft, scale, method="block", columns=COLUMNS_DEFAULT, store=None,
               progress=None):
    """The n_soft null vectors of M orthogonal to the d translations (a :class:`NullBasis`), by
    block inverse iteration (``block``, the default; much faster for hundreds of modes, see
    docs/results/benchmarks.md) in blocks of ``columns`` (None: one block) or by SLEPc
    Krylov-Schur shift-and-invert (``krylov``).  ``store`` (block only): a callable n_loc ->
    empty :class:`parjam.softmodes.scratch.ScratchBasis` that keeps the basis out of core.
    ``progress`` (block only): called with the number of null vectors found after each block."""
    if method == "block":
        return null_basis_block(comm, M, d, n_soft, scale, columns=columns, store=store,
                                progress=progress)
    if store is not None:
        raise ParjamError("an out-of-core basis (--scratch) needs the block method")
    if method == "krylov":
        return null_basis_krylov(comm, M, d, n_soft, scale)
    raise ParjamError(f"unknown basis method {method!r} (choose from {', '.join(BASIS_METHODS)})")


def null_basis_block(comm, M, d, n_soft, scale, prefix="soft_", oversample=8, tau=1e-8,
                     tol=1e-12, passes=3, max_rounds=5, columns=COLUMNS_DEFAULT, block=512,
                     seed=0, store=None, progress=None):
    """The n_soft null vectors of M orthogonal to the d translations, by block inverse
    (subspace) iteration with one MUMPS Cholesky factor of A = M + tau k I.

    Every null vector is amplified by 1/tau per solve, the rest by at most 1/(gap + tau): at
    tau = 1e-8 k and a gap of ~1e-5..1e-3 k (the inertia check proves >= 1e-6 k), ``passes``
    solves leave a contamination of < 1e-9, and a Rayleigh-Ritz step removes the rest.  The
    null space is exactly degenerate, so any block of it converges at that rate: the blocks of
    ``columns`` need no oversampling, only the last one carries the ``oversample`` extra
    columns.  The solves use MUMPS's multi-RHS path in blocks of ``block`` columns; the
    orthonormalisation and Rayleigh-Ritz are dense BLAS-3 on the local rows.
    ``-soft_ksp_*``/``-soft_pc_*`` options reach the factorisation, ``-soft_gap_eps_*`` the gap
    solve.  ``store``, ``progress``: see :func:`null_basis`.
    """
    lo, hi = M.getOwnershipRange()
    k = min(n_soft + oversample, M.getSize()[0] - d)
    columns = k if columns is None else int(columns)
    ksp = factorised(comm, M, tau * scale, prefix)
    T = translation_columns(M, d)
    V = np.empty((hi - lo, n_soft)) if store is None else store(hi - lo)
    theta = np.empty(n_soft)
    found, iterations = 0, 0
    try:
        while found < n_soft:
            last = n_soft - found <= columns
            width = k - found if last else columns
            need = min(width, n_soft - found)
            X = random_block(lo, hi, width, seed, first=found)
            Vb, tb, its = converged_block(comm, ksp, M, X, T,
                                          V[:, :found] if store is None else V, need, scale,
                                          passes, max_rounds, tol, block)
            if store is None:
                V[:, found:found + need] = Vb[:, :need]
            else:
                V.append(Vb[:, :need])
            theta[found:found + need] = tb[:need]
            found += need
            iterations = max(iterations, its)
            if progress is not None:
                progress(found)
        gap = gap_above(comm, ksp, (T, V), tau * scale, prefix + "gap_")
    finally:
        ksp.destroy()
    return NullBasis(V, theta, gap, lo // d, hi // d, iterations, "block-inverse")


def converged_block(comm, ksp, M, X, T, found, need, scale, passes, max_rounds, tol, block):
    """Inverse passes and Rayleigh-Ritz on the block X, kept orthogonal to the translations T
    and the null vectors ``found``, until its ``need`` lowest Ritz pairs have residuals below
    tol k and eigenvalues below 1e-6 k.  Returns (Ritz vectors, values, passes done)."""
    for rnd in range(1, max_rounds + 1):
        for _ in range(passes if rnd == 1 else 1):
            X = normalised_columns(comm, apply_inverse(comm, ksp, deflated(comm, X, T, found),
                                                       block))
        Vb, tb, res = rayleigh_ritz(comm, M, orthonormal(comm, deflated(comm, X, T, found)))
        if Vb.shape[1] >= need and res[:need].max() <= tol * scale \
                and tb[need - 1] <= 1e-6 * scale:
            return Vb, tb, passes + rnd - 1
        if Vb.shape[1] < need:
            raise ParjamError(f"block inverse iteration kept only {found.shape[1] + Vb.shape[1]}"
                              f" of the {found.shape[1] + need} null directions found so far",
                              collective=True)
        X = Vb
    raise ParjamError(f"block inverse iteration did not converge in {max_rounds} rounds "
                      f"(largest residual {res[:need].max() / scale:.1e} k; try "
                      "--basis krylov)", collective=True)


def factorised(comm, M, shift, prefix):
    """A KSP whose PC holds the MUMPS Cholesky factor of M + shift I (preonly)."""
    PETSc = env.petsc()
    A = M.copy()
    A.shift(shift)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOperators(A)
    factor.direct_cholesky(ksp)
    ksp.setOptionsPrefix(prefix)
    ksp.setFromOptions()
    try:
        ksp.setUp()
    except PETSc.Error as exc:
        raise ParjamError(f"the factorisation of M + tau k I failed (PETSc error {exc.ierr}; "
                          f"check the -{prefix}pc_* options)") from None
    finally:
        A.destroy()
    return ksp


def apply_inverse(comm, ksp, X, block):
    """(M + tau I)^-1 X, column block by column block (MUMPS multi-RHS solves)."""
    PETSc = env.petsc()
    nloc, k = X.shape
    n = comm.tompi4py().allreduce(nloc)
    Y = np.empty_like(X)
    pc = ksp.getPC()
    for a in range(0, k, block):
        z = min(k, a + block)
        B = PETSc.Mat().createDense(((nloc, n), (PETSc.DECIDE, z - a)), comm=comm,
                                    array=np.asfortranarray(X[:, a:z]))
        C = PETSc.Mat().createDense(((nloc, n), (PETSc.DECIDE, z - a)), comm=comm)
        C.setUp()
        pc.matApply(B, C)
        Y[:, a:z] = C.getDenseArray()
        B.destroy()
        C.destroy()
    return Y


def gap_above(comm, ksp, bases, shift, prefix="soft_gap_", tol=1e-8):
    """Lowest eigenvalue of M in the complement of the orthonormal, mutually orthogonal
    ``bases`` (translations and null basis, kept apart: no joined copy): the largest eigenvalue
    1 / (lambda + shift) of P A^-1 P, P = I - sum U U^T, by SLEPc Krylov-Schur on a shell
    operator that reuses the factor in ``ksp``."""
    PETSc, SLEPc = env.petsc(), env.slepc()
    A = ksp.getOperators()[0]
    if A.getSize()[0] - sum(U.shape[1] for U in bases) <= 0:
        return np.inf
    op = PETSc.Mat().createPython(A.getSizes(), ProjectedInverse(comm, ksp, bases), comm=comm)
    op.setUp()
    eps = SLEPc.EPS().create(comm=comm)
    try:
        eps.setOperators(op)
        eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
        eps.setDimensions(1, PETSc.DECIDE)
        eps.setWhichEigenpairs(SLEPc.EPS.Which.LARGEST_MAGNITUDE)
        eps.setTolerances(tol)
        eps.setOptionsPrefix(prefix)
        eps.setFromOptions()
        eps.solve()
        if not eps.getConverged():
            return np.nan
        return float(1.0 / eps.getEigenvalue(0).real - shift)
    finally:
        eps.destroy()
        op.getPythonContext().work.destroy()
        op.destroy()


class ProjectedInverse:
    """y = P A^-1 P x with P = I - sum U U^T over ``bases`` (petsc4py shell-matrix context)."""

    def __init__(self, comm, ksp, bases):
        self.comm, self.ksp, self.bases = comm, ksp, bases
        self.work = ksp.getOperators()[0].createVecRight()

    def project(self, a):
        for U in self.bases:
            for B in column_blocks(U):
                a = a - B @ allreduce(self.comm, B.T @ a)
        return a

    def mult(self, mat, x, y):
        self.work.setArray(self.project(x.getArray(readonly=True)))
        self.ksp.solve(self.work, y)
        y.setArray(self.project(y.getArray(readonly=True)))
