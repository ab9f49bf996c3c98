"""Direct Cholesky (LDL^T) factorisations through PETSc, and their inertia: one place for the
choice of MUMPS and its settings, used by Newton (parjam.pack.minimize), shift-and-invert
(parjam.vib.spectrum, parjam.softmodes), the response solves (parjam.vib.moduli) and the eigenvalue
counts (parjam.softmodes.count_below).

The inertia of the factor of a symmetric A - s I counts the eigenvalues of A below s (Sylvester's
law of inertia).  MUMPS reports it for LDL^T factorisations (INFOG(12), MatGetInertia); on several
ranks it factorises the root front with ScaLAPACK, which does not count pivots, so ICNTL(13) = 1
keeps that front sequential (see ``exact_inertia``).
"""

from parjam import env


def use_cholesky(pc, fallback=None):
    """Make ``pc`` a Cholesky (LDL^T for indefinite matrices) factorisation, by MUMPS when this
    PETSc has it; otherwise by PETSc's own, or by the PC type ``fallback`` if given.  Returns
    True when MUMPS is used.  Options given later (setFromOptions) still override all of it."""
    pc.setType("cholesky")
    if env.has_mumps():
        pc.setFactorSolverType("mumps")
        return True
    if fallback is not None:
        pc.setType(fallback)
    return False


def direct_cholesky(ksp, fallback=None):
    """Make ``ksp`` one direct solve (preonly) with ``use_cholesky``; returns use_cholesky's."""
    ksp.setType("preonly")
    return use_cholesky(ksp.getPC(), fallback)


def is_mumps_cholesky(pc):
    return pc.getType() == "cholesky" and pc.getFactorSolverType() == "mumps"


def exact_inertia(pc, null_pivots=False, inertia_only=False):
    """Ask MUMPS (if ``pc`` is a MUMPS Cholesky) for an exact inertia on any number of ranks:
    ICNTL(13) = 1, the root front factorised sequentially.  ``null_pivots`` also sets
    ICNTL(24) = 1 (null pivot detection: a singular A still factorises, its zero pivots
    counted).  ``inertia_only`` sets ICNTL(31) = 1: MUMPS discards the factors as it computes
    them, for a factorisation that is asked only for its inertia (stability checks, null-space
    counts; no solve can follow).  Its peak memory is then the frontal stack alone: 703 MB
    instead of 1314 MB for the stability check at 98k dof (docs/explanation/scaling.md, "Counting without
    keeping the factor").  Call after the operators are set and before setUp; options given
    under the object's prefix still win."""
    if not is_mumps_cholesky(pc):
        return
    pc.setFactorSetUpSolverType()
    F = pc.getFactorMatrix()
    if pc.comm.getSize() > 1:  # one rank has no ScaLAPACK front
        F.setMumpsIcntl(13, 1)
    if null_pivots:
        F.setMumpsIcntl(24, 1)
    if inertia_only:
        F.setMumpsIcntl(31, 1)


def negative_pivots(pc):
    """Number of negative pivots of a factorised MUMPS LDL^T (INFOG(12)): the number of negative
    eigenvalues of the factorised matrix; None when ``pc`` is not a MUMPS Cholesky."""
    if not is_mumps_cholesky(pc):
        return None
    return int(pc.getFactorMatrix().getMumpsInfog(12))
