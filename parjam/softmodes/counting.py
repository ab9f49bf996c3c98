"""Counting soft modes exactly (Wyart et al. 2005, Sec. II): the null-space dimension of the cut
system from MUMPS inertia.  Cutting q contacts of a network Nc - Nc_iso from isostatic leaves
d + q - 1 - (Nc - Nc_iso) zero modes (d translations included, Nc_iso = d(N' - 1) + 1; for an
isostatic packing d + q - 1, :attr:`parjam.softmodes.cut.CutSystem.expected`)."""

from parjam import env
from parjam.vib import factor
from parjam.errors import ParjamError


def expected_zero_modes(d, q, excess):
    """d + q - 1 - (Nc - Nc_iso) (Sec. II): the rigidity matrix of Nc contacts among N'
    particles has Nc - Nc_iso + 1 self-stresses (isostatic: one); each cut first removes one of
    them, then opens a floppy mode, so once q > Nc - Nc_iso the null space is the d translations
    plus q - 1 - (Nc - Nc_iso) floppy modes."""
    return d + q - 1 - excess


def count_below(comm, M, s, prefix="soft_inertia_"):
    """Number of eigenvalues of the symmetric M below s: the negative inertia of M - s I from a
    MUMPS LDL^T factorisation (SBAIJ; ICNTL(13) = 1 makes the inertia exact on several ranks).
    M is best assembled as SBAIJ (parjam.vib.hessian.assemble(fmt="sbaij")); an AIJ M is
    converted."""
    PETSc = env.petsc()
    A = M.copy()
    A.shift(-s)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    As = A.convert("sbaij") if "sbaij" not in A.getType() else A
    pc = PETSc.PC().create(comm=comm)
    try:
        pc.setOptionsPrefix(prefix)
        pc.setOperators(As)
        factor.use_cholesky(pc)
        factor.exact_inertia(pc, null_pivots=True, inertia_only=True)
        pc.setFromOptions()
        pc.setUp()
        neg, zero, _ = pc.getFactorMatrix().getInertia()
    finally:
        pc.destroy()
        if As is not A:
            As.destroy()
        A.destroy()
    return int(neg) + int(zero)


def gap_counts(comm, M, scale, thresholds, prefix="soft_inertia_"):
    """Eigenvalues of M below t * scale for each t in ``thresholds``.  Counts that differ are
    taken once more, each by a fresh factorisation, and the second set is returned: MUMPS's
    parallel LDL^T was seen to return a wrong inertia now and then on 8 oversubscribed ranks
    (docs/explanation/scaling.md, "Soft modes on the distributed network"), while a genuine lack of gap
    gives the same differing counts again."""
    counts = [count_below(comm, M, t * scale, prefix=prefix) for t in thresholds]
    if len(set(counts)) > 1:
        counts = [count_below(comm, M, t * scale, prefix=prefix) for t in thresholds]
    return counts


def null_count(comm, M, scale, thresholds=(1e-10, 1e-6)):
    """Null-space dimension of the PSD matrix M: eigenvalues below t * scale, counted by inertia
    at both thresholds (``gap_counts``); a different count means no clear gap (ParjamError)."""
    counts = gap_counts(comm, M, scale, thresholds)
    if counts[0] != counts[1]:
        raise ParjamError(
            f"no spectral gap around zero: {counts[0]} eigenvalues below {thresholds[0]:g} k "
            f"but {counts[1]} below {thresholds[1]:g} k; the null space is ill-defined "
            "(nearly floppy contacts?)")
    return counts[0]


def variational_count(comm, M_uncut, omega_t2):
    """Number of true eigenmodes of the uncut M with omega^2 < 2 omega_t^2 (inertia): the
    variational argument of Sec. III needs at least q'/2 of them."""
    return count_below(comm, M_uncut, 2.0 * omega_t2)
