"""Vibrational spectra of the dynamical matrices of Eq. (1): the full D = M + M', the
relaxed-spring M (Section III) and the stress term M' alone, for the non-rattlers of a packing.

Methods (docs/howto/spectra.md):

- ``dense``: LAPACK (scipy.linalg.eigh) on the dense matrix with the d uniform translations moved
  above the spectrum (Hotelling deflation): the exact small-system reference;
- ``sinvert``: the k eigenvalues nearest a target slightly below zero, SLEPc Krylov-Schur with
  shift-and-invert, MUMPS Cholesky (LDL^T) of D - target I, the d translations removed by a
  deflation space (EPSSetDeflationSpace) and an absolute convergence test;
- ``slice``: every eigenvalue in an interval, SLEPc spectrum slicing (SBAIJ + MUMPS with
  ICNTL(13) = 1 for the inertia), the count checked against the inertias at the interval ends.

Every pair carries its true residual ||D v - lambda v||_2 / ||D||_inf (the infinity norm bounds
the spectral norm of a symmetric matrix).  Pairs above the tolerance are dropped and reported,
never silently kept.  Eigenvectors are formed one at a time for the per-mode observables
(participation ratio, transverse/longitudinal sums, computed in parallel), and gathered to rank 0
only when asked for.

SLEPc/PETSc objects use the options prefix ``modes_`` (``-modes_eps_view``,
``-modes_st_mat_mumps_icntl_7 5``, ``-modes_eps_krylovschur_partitions 2`` ...).
The choice of method for ``auto`` is parjam.vib.solver_choice's.

Why one file of ~650 lines: the three methods return the same :class:`Spectrum` with the same
checks (residuals, zero cluster, inertia counts) and are tested against each other; the system
(this rank's share of parjam.net.active), the dense path (its linear algebra in
parjam.vib.dense), the SLEPc set-up and the collection of pairs are its sections.
"""

import copy
import time
from dataclasses import dataclass, field

import numpy as np

from parjam import env
from parjam.errors import ParjamError, UnjammedError
from parjam.net import active
from parjam.net.blocks import contact_blocks
from parjam.vib import factor, hessian, observables, solver_choice, translations
from parjam.vib.solver_choice import MATRICES, METHODS
from parjam.vib.dense import (DenseSystem, count_below_dense, deflated_dense, dense_eigh,
                              dense_matrix)

DENSE_LIMIT_DOF = 20000  # --method dense refused above (a 20000^2 matrix is 3.2 GB)
ZERO_TOL = 1e-9  # |lambda| / ||D||_inf below which an eigenvalue belongs to the zero cluster
PREFIX = "modes_"


# --- the system: non-rattlers re-indexed 0..N'-1 ---------------------------------------------------
@dataclass
class ActiveSystem:
    """This rank's share of the non-rattlers of a packing (N' of them, numbered 0..N'-1 by
    parjam.net.active) and their contacts: the owned rows ``rows`` = (lo, hi), the particle ids
    ``ids`` of those rows, and the half-edges (i owned in [lo, hi), j any; every contact once
    per end).  One rank is P = 1 of the same layout."""

    n: int
    d: int
    i: np.ndarray
    j: np.ndarray
    rij: np.ndarray
    r: np.ndarray
    sigma: np.ndarray
    alpha: float
    eps: float
    n_rattlers: int
    n_iso: int
    pressure: float
    max_force: float
    rows: tuple
    ids: np.ndarray
    n_contacts: int  # Nc over all ranks (the half-edges are this rank's)

    @property
    def dof(self):
        return self.n * self.d

    @property
    def n_modes(self):
        """Non-translational modes: d N' - d."""
        return observables.n_modes_total(self.n, self.d)

    def blocks(self, kind):
        """Per-half-edge blocks K_ij of Eq. (1)."""
        return contact_blocks(self.rij, self.r, self.sigma, self.alpha, self.eps, kind)

    def gather_ids(self, comm):
        """Collective: on rank 0 the particle ids of every row in active-number order (None
        elsewhere)."""
        got = comm.tompi4py().gather(self.ids, root=0)
        return None if got is None else np.concatenate(got)

    def gathered(self, comm):
        """Collective: the whole system on rank 0 (None elsewhere) as a dense.DenseSystem, rows
        in ascending particle id and every contact once (i < j): the dense path's input, for
        small systems only."""
        up = self.i < self.j
        parts = comm.tompi4py().gather((self.i[up], self.j[up], self.rij[up], self.r[up],
                                        self.sigma[up]), root=0)
        ids = self.gather_ids(comm)
        if parts is None:
            return None
        i, j, rij, r, sigma = (np.concatenate(col) for col in zip(*parts))
        order = np.argsort(ids)  # active number -> rank in particle-id order
        rank = np.argsort(order)
        i, j = rank[i], rank[j]
        flip = i > j
        i, j = np.where(flip, j, i), np.where(flip, i, j)
        rij = np.where(flip[:, None], -rij, rij)
        return DenseSystem(n=self.n, d=self.d, ids=ids[order], i=i, j=j, rij=rij, r=r,
                           sigma=sigma, alpha=self.alpha, eps=self.eps)


def check_vibrates(n, d, n_all_contacts, n_active, n_contacts, n_iso):
    """ParjamError/UnjammedError for a network that cannot vibrate."""
    if n_all_contacts == 0:
        raise ParjamError("the packing has no contacts (no overlapping pairs): nothing to "
                          "vibrate; is it a jammed packing?")
    if n_active == 0:
        raise UnjammedError(f"unjammed packing: all {n} particles are rattlers")
    if n_contacts < n_iso:
        raise UnjammedError(f"unjammed packing: Nc = {n_contacts} contacts among "
                            f"N' = {n_active} non-rattlers, fewer than the isostatic "
                            f"Nc_iso = {n_iso}: at least {n_iso - n_contacts} "
                            f"floppy mode(s) beyond the {d} translations")


def system_of(comm, pack):
    """The non-rattler system of a packing every rank of ``comm`` holds (tests, small systems):
    each rank starts from its row block of the packing, as if it had read only that."""
    return distributed_system(active.from_packing(comm, pack))


def distributed_system(net):
    """The non-rattler system of a distributed network (parjam.net.active): this rank's rows and
    half-edges only; ParjamError/UnjammedError if it cannot vibrate (collective)."""
    check_vibrates(net.n, net.d, net.n_all_contacts, net.n_active, net.n_contacts, net.n_iso)
    c = net.contacts
    return ActiveSystem(
        n=net.n_active, d=net.d, i=c.i, j=c.j, rij=c.rij, r=c.r, sigma=c.sigma,
        alpha=net.alpha, eps=net.eps, n_rattlers=net.n_rattlers, n_iso=net.n_iso,
        pressure=net.pressure, max_force=net.max_force, rows=net.rows, ids=net.ids,
        n_contacts=net.n_contacts)


def build_matrix(comm, system, blocks, fmt="aij"):
    """Distributed MatAIJ or MatSBAIJ (block size d) from per-contact (per-half-edge) blocks:
    each rank inserts its own rows only."""
    return hessian.assemble(comm, system.n, system.d, system.i, system.j, blocks,
                            rows=system.rows, fmt=fmt)


def dynamical_matrix(comm, system, kind, fmt="aij"):
    """Eq. (1): the full, relaxed or stress matrix of the non-rattlers, in the solver's format
    (SBAIJ for MUMPS Cholesky and its inertia, AIJ for products and KSP)."""
    return build_matrix(comm, system, system.blocks(kind), fmt)


# --- results ---------------------------------------------------------------------------------------
@dataclass
class Spectrum:
    """Accepted eigenpairs (ascending) and everything needed to judge them."""

    eigenvalue: np.ndarray
    error: np.ndarray  # ||D v - lambda v|| / ||D||_inf
    participation_ratio: np.ndarray
    eps_perp: np.ndarray
    eps_par: np.ndarray
    matrix: str
    method: str
    tolerance: float
    norm: float  # ||D||_inf
    n_requested: int  # k, or the inertia count of the window
    target: float = float("nan")
    interval: tuple = (float("nan"), float("nan"))  # lambda interval of a window
    n_unstable: int = -1  # eigenvalues below -zero_tol (inertia; -1 if not known)
    rejected_eigenvalue: np.ndarray = field(default_factory=lambda: np.zeros(0))
    rejected_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    vectors: np.ndarray = None  # (K, n_rows, d) when asked for: this rank's active rows,
    # particle ids ``vector_ids``
    vector_ids: np.ndarray = None
    info: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def frequency(self):
        return observables.frequency(self.eigenvalue)

    @property
    def n_missing(self):
        return self.n_requested - len(self.eigenvalue)

    @property
    def complete(self):
        return self.n_missing == 0 and len(self.rejected_eigenvalue) == 0

    @property
    def zero_tol(self):
        return ZERO_TOL * self.norm

    @property
    def n_negative(self):
        """Eigenvalues below -zero_tol (beyond round-off), from the inertia when known."""
        return max(int(np.sum(self.eigenvalue < -self.zero_tol)), self.n_unstable)

    @property
    def n_zero(self):
        """Accepted eigenvalues inside the zero cluster |lambda| <= zero_tol: floppy modes beyond
        the d deflated translations (a hypostatic network), never physical vibrations."""
        return int(np.sum(np.abs(self.eigenvalue) <= self.zero_tol))

    @property
    def physical(self):
        """Mask of the accepted eigenvalues above the zero cluster (vibrations)."""
        return self.eigenvalue > self.zero_tol

    @property
    def unstable(self):
        """Negative eigenvalues of the full or relaxed matrix beyond round-off (the stress term
        alone is indefinite by nature)."""
        return self.matrix != "stress" and self.n_negative > 0


def choose_method(method, dof, window, k=None, n_modes=None, tol=None):
    """``auto``: the choice of parjam.vib.solver_choice (the crossovers measured in
    docs/results/speed-accuracy.md) for the k lowest modes or a window (a window wins when both are
    given); any other method is returned as it is."""
    if method != "auto":
        return method
    return solver_choice.choose_solver(dof, n_modes, k=k if window is None else None,
                                       window=window, tol=tol)


#: where a window is cut off: every eigenvalue has |lambda| <= ||D||_inf (Gershgorin), and the
#: dense path's deflated translations sit at 2 ||D||_inf (deflated_dense), so a window reaching
#: past the spectrum ends between the two (else it would collect the translations as modes)
SPECTRUM_EDGE = 1.5


def window_interval(window, norm):
    """lambda interval of a frequency window [wa, wb] (negative omega: negative lambda), an end
    inside the zero cluster moved just outside it (slicing cannot start on the translations),
    an end beyond the spectrum (|lambda| > ||D||_inf) moved to SPECTRUM_EDGE ||D||_inf: no
    overflow of omega^2, no deflated translation inside."""
    wa, wb = window
    if not (np.isfinite(wa) and np.isfinite(wb)) or wb <= wa:
        raise ParjamError(f"empty frequency window [{wa}, {wb}]: need WA < WB")
    edge = np.sqrt(SPECTRUM_EDGE * norm)  # omega of the cut-off
    if wa >= edge or wb <= -edge:
        raise ParjamError(f"frequency window [{wa}, {wb}] holds no mode: every |omega| is at "
                          f"most sqrt(||D||_inf) = {np.sqrt(norm):.4g}")
    wa, wb = max(wa, -edge), min(wb, edge)
    la, lb = np.sign(wa) * wa * wa, np.sign(wb) * wb * wb
    tol = ZERO_TOL * norm
    if la >= -tol and lb <= tol:
        raise ParjamError(f"frequency window [{wa}, {wb}] holds no nonzero mode: it lies in the "
                          f"zero cluster |omega| < {np.sqrt(tol):.2e}")
    if la < -tol and lb > tol:
        raise ParjamError(f"frequency window [{wa}, {wb}] spans the d translations at zero: "
                          f"ask for [{wa}, 0] and [0, {wb}] separately")
    if abs(la) <= tol:
        la = tol
    if abs(lb) <= tol:
        lb = -tol
    return la, lb


def check_k(k, system):
    if k is None or k < 1:
        raise ParjamError(f"--k must be a positive number of modes, got {k}")
    if k > system.n_modes:
        raise ParjamError(f"--k {k} exceeds the {system.n_modes} non-translational modes "
                          f"(d N' - d with N' = {system.n} non-rattlers, d = {system.d})")


def compute(comm, system, kind="full", *, k=None, window=None, method="auto", tol=1e-10,
            target=None, vectors=False, progress=None):
    """Spectrum of one matrix of a system by the chosen method (see module doc)."""
    if kind not in MATRICES:
        raise ParjamError(f"unknown matrix {kind!r}; choose from {', '.join(MATRICES)}")
    if method not in METHODS:
        raise ParjamError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    if (k is None) == (window is None):
        raise ParjamError("give either a number of modes (--k) or a frequency window (--window)")
    solver_choice.check_tol(tol)
    if k is not None:
        check_k(k, system)
    method = choose_method(method, system.dof, window, k, system.n_modes, tol)
    if method == "slice" and window is None:
        raise ParjamError("--method slice needs --window WA,WB")
    if method == "dense" and system.dof > DENSE_LIMIT_DOF:
        raise ParjamError(f"--method dense refused for {system.dof} degrees of freedom (limit "
                          f"{DENSE_LIMIT_DOF}): use sinvert or slice")
    t0 = time.perf_counter()
    if method == "dense":
        spec = dense_modes(comm, system, kind, k=k, window=window, tol=tol,
                           want_vectors=vectors)
    else:
        S = dynamical_matrix(comm, system, kind, fmt="sbaij")
        try:
            spec = slepc_modes(comm, S, system, kind=kind, method=method, k=k, window=window,
                               tol=tol, target=target, want_vectors=vectors, progress=progress)
        finally:
            S.destroy()
    spec.seconds = time.perf_counter() - t0
    return spec


def vectors_on_root(comm, spec):
    """A spectrum's eigenvectors (K, N', d) on rank 0 of ``comm`` in particle-id order, from
    each rank's rows (``vector_ids``); None elsewhere (collective; a gather of K d N' numbers:
    for records and tests, not for files)."""
    mpi = comm.tompi4py()
    ids = mpi.gather(spec.vector_ids, root=0)
    rows = mpi.gather(spec.vectors.transpose(1, 0, 2), root=0)
    if mpi.Get_rank() != 0:
        return None
    return np.concatenate(rows)[np.argsort(np.concatenate(ids))].transpose(1, 0, 2)


# --- dense LAPACK (parjam.vib.dense) ------------------------------------------------------------
def dense_modes(comm, system, kind, *, k, window, tol, want_vectors):
    """The dense path (parjam.vib.dense): the system gathered and solved on rank 0 of ``comm``,
    the spectrum broadcast and the eigenvectors, when asked for, sent back to the ranks that own
    their rows (each rank's (K, rows, d) with ``vector_ids``, as the SLEPc paths leave them)."""
    mpi = comm.tompi4py()
    spec, message = None, None
    whole = system.gathered(comm)  # rows in ascending particle id (the file's order)
    if mpi.Get_rank() == 0:
        try:
            spec = _dense_on_rank0(whole, kind, k, window, tol, want_vectors)
        except ParjamError as exc:
            message = str(exc)
    message = mpi.bcast(message)
    if message:
        raise ParjamError(message)
    vectors = spec.vectors if spec is not None else None
    if spec is not None:
        spec = copy.copy(spec)
        spec.vectors = None
    spec = mpi.bcast(spec) if mpi.Get_size() > 1 else spec
    if want_vectors:
        spec.vectors = owned_rows(mpi, whole, vectors, system.ids)
        spec.vector_ids = np.asarray(system.ids)
    return spec


def owned_rows(mpi, whole, vectors, ids):
    """Each rank's rows (K, len(ids), d) of the (K, N', d) ``vectors`` rank 0 holds in the order
    of ``whole.ids`` (collective: rank 0 sends every rank its rows, one rank at a time)."""
    wanted = mpi.gather(np.asarray(ids), root=0)
    mine = None
    if mpi.Get_rank() == 0:
        for r, want in enumerate(wanted):
            block = np.ascontiguousarray(vectors[:, np.searchsorted(whole.ids, want), :])
            if r == 0:
                mine = block
            else:
                mpi.send(block, dest=r, tag=OWNED_TAG)
    else:
        mine = mpi.recv(source=0, tag=OWNED_TAG)
    return mine


OWNED_TAG = 7302  # point-to-point tag of the eigenvector rows sent back to their owners


def _dense_on_rank0(system, kind, k, window, tol, want_vectors):
    H = dense_matrix(system, kind)
    norm = float(np.abs(H).sum(axis=1).max())
    Hd = deflated_dense(H, system.n, system.d, norm)
    interval = window_interval(window, norm) if window is not None else None
    n_unstable = count_below_dense(Hd, -ZERO_TOL * norm)
    lam, V = dense_eigh(Hd, k=k, interval=interval, vectors=True)
    if window is not None and len(lam) == 0:
        raise ParjamError(f"frequency window [{window[0]}, {window[1]}] holds no eigenvalue")
    err = np.linalg.norm(H @ V - V * lam, axis=0) / norm
    vec3 = V.T.reshape(len(lam), system.n, system.d)
    ok = err <= tol
    perp, par = observables.transverse_longitudinal(vec3[ok], system.i, system.j, system.rij,
                                                    system.r)
    return Spectrum(
        eigenvalue=lam[ok], error=err[ok],
        participation_ratio=observables.participation_ratio(vec3[ok]), eps_perp=perp,
        eps_par=par, matrix=kind, method="dense", tolerance=tol, norm=norm,
        n_requested=k if k is not None else len(lam),
        interval=tuple(interval) if interval else (float("nan"),) * 2, n_unstable=n_unstable,
        rejected_eigenvalue=lam[~ok], rejected_error=err[~ok],
        vectors=vec3[ok] if want_vectors else None,
        info={"solver": "scipy.linalg.eigh of D + 2 ||D||_inf T T^T (translations T moved above "
                        "the spectrum)",
              "inertia": f"{n_unstable} eigenvalues below -zero_tol (LDL^T)"})


# --- SLEPc paths ---------------------------------------------------------------------------------
def configure_sinvert(eps):
    """Shift-and-invert with a direct MUMPS Cholesky (LDL^T) factorisation, no Krylov solve."""
    st = eps.getST()
    st.setType("sinvert")
    factor.direct_cholesky(st.getKSP())


def finish_setup(eps, S):
    """The EPS's own options (prefix ``modes_``), then MUMPS ICNTL(13) = 1 and ICNTL(24) = 1 on
    this EPS's factor only (never through the options database): on more than one rank MUMPS
    counts pivots (the inertia that slicing and the unstable count need) only with a sequential
    root front, and null pivots let a floppy network factorise.  Options the user gives under
    the prefix (-modes_st_mat_mumps_icntl_13 ...) still win: MUMPS reads them at the analysis.
    With -modes_eps_krylovschur_partitions > 1 SLEPc builds inner solvers from the options
    alone; give -modes_st_mat_mumps_icntl_13 1 then."""
    eps.setOptionsPrefix(PREFIX)
    eps.setFromOptions()
    ksp = eps.getST().getKSP()
    ksp.setOperators(S)  # SLEPc replaces it by S - sigma I at setUp; the factor object stays
    factor.exact_inertia(ksp.getPC(), null_pivots=True)


def sinvert_eps(A, k, target, abstol, deflation):
    """Krylov-Schur for the k eigenvalues nearest ``target`` (slightly below zero), translations
    deflated, absolute convergence test."""
    SLEPc = env.slepc()
    eps = SLEPc.EPS().create(A.getComm())
    eps.setOperators(A)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
    # ncv = 1.5 k (SLEPc's default is 2 k): fewer solves in total at k = 100 (measured in
    # docs/results/benchmarks.md); -modes_eps_ncv overrides
    eps.setDimensions(nev=k, ncv=k + max(k // 2, 20))
    eps.setTarget(target)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    eps.setConvergenceTest(SLEPc.EPS.Conv.ABS)
    eps.setTolerances(tol=abstol)
    eps.setDeflationSpace(deflation)
    configure_sinvert(eps)
    finish_setup(eps, A)
    return eps


def slice_eps(S, interval, abstol):
    """Spectrum slicing of the SBAIJ matrix S over a lambda interval (every eigenvalue in it)."""
    SLEPc = env.slepc()
    eps = SLEPc.EPS().create(S.getComm())
    eps.setOperators(S)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
    eps.setInterval(*interval)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.ALL)
    eps.setConvergenceTest(SLEPc.EPS.Conv.ABS)
    eps.setTolerances(tol=abstol)
    configure_sinvert(eps)
    finish_setup(eps, S)
    # slicing factorises in an inner EPS that copies only the ST/KSP/PC types: its MUMPS
    # Cholesky and ICNTLs are set on its own KSP (one partition: same communicator as S)
    inner = eps.getKrylovSchurKSP()
    factor.direct_cholesky(inner)
    if eps.getKrylovSchurPartitions() == 1:
        inner.setOperators(S)
        factor.exact_inertia(inner.getPC(), null_pivots=True)
    return eps


def mumps_stats(F):
    """Fill, ordering and flops of a MUMPS factor (INFOG/RINFOG) for the report."""
    orderings = {0: "AMD", 1: "user", 2: "AMF", 3: "SCOTCH", 4: "PORD", 5: "METIS", 6: "QAMD"}
    try:
        fill = F.getMumpsInfog(29)
        fill = -fill * 1_000_000 if fill < 0 else fill
        seq = F.getMumpsInfog(7)
        par = F.getMumpsInfog(32) if hasattr(F, "getMumpsInfog") else 0
        return {"factor_entries": int(fill), "flops": float(F.getMumpsRinfog(1)),
                "ordering": orderings.get(seq, str(seq)) if par != 2 else "parallel (ICNTL 29)",
                "analysis": "parallel" if par == 2 else "sequential"}
    except Exception:  # an older PETSc without the accessors: report nothing
        return {}


def slepc_modes(comm, S, system, *, kind, method, tol, k=None, window=None, target=None,
                want_vectors=False, progress=None):
    """The k lowest modes (method "sinvert", shift-and-invert at ``target``) or the modes in a
    frequency ``window`` (method "slice", spectrum slicing) of the assembled SBAIJ matrix S of
    one ``kind`` (MUMPS reports the inertia of SBAIJ factors only), to residual ``tol``
    relative to ||S||_inf, with their observables."""
    PETSc = env.petsc()
    norm = S.norm(PETSc.NormType.INFINITY)
    zero_tol = ZERO_TOL * norm
    abstol = 0.1 * tol * norm  # SLEPc's estimate, with a margin for the true residual check
    log = progress or (lambda msg: None)
    deflation = []
    if method == "sinvert":
        target = -zero_tol if target is None else float(target)
        if abs(target) < zero_tol:  # D - target I singular beyond the deflated translations
            raise ParjamError(f"--target {target:g} lies inside the zero cluster |lambda| < "
                              f"{zero_tol:.2e}, where the shifted matrix is singular for a "
                              f"floppy network: use a target <= {-zero_tol:.2e} (the default)")
        deflation = translations.vectors(S, system.d)
        eps = sinvert_eps(S, k, target, abstol, deflation)
    else:
        # slicing's estimates (Ritz residuals of the shifted, inverted problem of each
        # sub-interval) undershot the true residual by up to 19x (2D relaxed test matrix:
        # 1.16e-10 against the 0.1 tol asked): a margin of 100 accepts every pair there
        eps = slice_eps(S, window_interval(window, norm), 0.1 * abstol)
    try:
        with SliceInertiaOptions(comm if method == "slice" else None):
            spec = _solve_and_collect(comm, eps, S, system, kind=kind, method=method, k=k,
                                      window=window, tol=tol, norm=norm, target=target,
                                      want_vectors=want_vectors, log=log)
    finally:
        try:
            eps.destroy()
        except PETSc.Error:  # after a failed solve SLEPc may refuse (a DS matrix checked
            pass  # out): the solve's own error, already raised, is the one to report
        translations.destroy(deflation)
    return spec


class SliceInertiaOptions:
    """The one place parjam writes PETSc options: -modes_st_mat_mumps_icntl_13 1 and _24 1,
    only while a slicing solve runs on more than one rank, only those the user did not give,
    removed after.  Why: slicing re-creates its MUMPS factor whenever the shifted matrix is a
    new object (SLEPc's inner EPS, PCSetUp with a different nonzero state), so ICNTLs set on a
    factor object are lost, and the only settings the new factor reads are its prefix's
    options (``modes_st_``, the prefix of this EPS's ST, no other object's).  MUMPS needs
    ICNTL(13) = 1 on several ranks to count pivots; ICNTL(24) = 1 for MatGetInertia."""

    NAMES = ("st_mat_mumps_icntl_13", "st_mat_mumps_icntl_24")

    def __init__(self, comm):
        self.active = comm is not None and comm.getSize() > 1 and env.has_mumps()
        self.ours = []

    def __enter__(self):
        if self.active:
            opts = env.petsc().Options()
            for name in self.NAMES:
                if not opts.hasName(PREFIX + name):
                    opts.setValue(PREFIX + name, "1")
                    self.ours.append(PREFIX + name)
        return self

    def __exit__(self, *exc):
        opts = env.petsc().Options()
        for name in self.ours:
            opts.delValue(name)


def _solve_and_collect(comm, eps, A, system, *, kind, method, k, window, tol, norm, target,
                       want_vectors, log):
    PETSc = env.petsc()
    zero_tol = ZERO_TOL * norm
    stage = PETSc.Log.Stage("modes: eigensolve")
    stage.push()
    try:
        log(f"{method}: {kind} matrix, {A.getSize()[0]} dof, ||D||_inf = {norm:.4g}")
        eps.solve()
    except PETSc.Error as exc:
        why = str(exc).strip().splitlines()[-1].split("] ", 1)[-1]  # the stack's message
        raise ParjamError(f"SLEPc {method} failed: {why}") from None
    finally:
        stage.pop()
    info = {"iterations": eps.getIterationNumber(), "converged": eps.getConverged()}
    if method == "sinvert":
        F = eps.getST().getKSP().getPC().getFactorMatrix()
        n_unstable = F.getInertia()[0] if target <= -zero_tol else -1
        info.update(mumps_stats(F))
        spec = _collect(comm, eps, A, system, kind=kind, method=method, n_wanted=k, tol=tol,
                        norm=norm, want_vectors=want_vectors, log=log)
        spec.target, spec.n_unstable = target, int(n_unstable)
    else:
        interval = eps.getInterval()
        shifts, inertias = eps.getKrylovSchurInertias()
        count = int(inertias[-1] - inertias[0])
        if count == 0:
            raise ParjamError(f"frequency window [{window[0]}, {window[1]}] holds no "
                              f"eigenvalue (inertia count 0)")
        info.update({"inertia_shifts": [float(s) for s in shifts],
                     "inertias": [int(i) for i in inertias], "below_window": int(inertias[0])})
        spec = _collect(comm, eps, A, system, kind=kind, method=method, n_wanted=count, tol=tol,
                        norm=norm, want_vectors=want_vectors, log=log)
        spec.interval = tuple(interval)
        if interval[0] == zero_tol:  # below it: the d translations and unstable modes
            spec.n_unstable = int(inertias[0]) - system.d
    spec.info.update(info)
    return spec


class _ModeObservables:
    """Participation ratio and transverse/longitudinal sums of distributed eigenvectors:
    local reductions and products with the assembled unit-block matrices (no gathering)."""

    def __init__(self, comm, system):
        self.mpi = comm.tompi4py()
        self.n, self.d = system.n, system.d
        self.par = build_matrix(comm, system, observables.unit_blocks(system.rij, system.r, "par"))
        self.perp = build_matrix(comm, system,
                                 observables.unit_blocks(system.rij, system.r, "perp"))
        self.w = self.par.createVecLeft()

    def __call__(self, v):
        loc = v.getArray(readonly=True).reshape(-1, self.d)
        w2 = np.einsum("ia,ia->i", loc, loc)
        s2, s4 = self.mpi.allreduce(np.array([w2.sum(), (w2 * w2).sum()]))
        self.par.mult(v, self.w)
        e_par = 0.5 * self.w.dot(v) / s2
        self.perp.mult(v, self.w)
        e_perp = 0.5 * self.w.dot(v) / s2
        return s2 * s2 / (self.n * s4), e_perp, e_par

    def destroy(self):
        for obj in (self.par, self.perp, self.w):
            obj.destroy()


def _collect(comm, eps, A, system, *, kind, method, n_wanted, tol, norm, want_vectors, log):
    """Accepted pairs (true residual <= tol), their observables and vectors: each rank keeps
    its own rows (no rank holds all N')."""
    PETSc = env.petsc()
    SLEPc = env.slepc()
    stage = PETSc.Log.Stage("modes: observables")
    stage.push()
    nconv = eps.getConverged()
    take = min(nconv, n_wanted)
    obs = _ModeObservables(comm, system)
    v = A.createVecRight()
    rows = []
    vecs = []
    for idx in range(take):
        lam = eps.getEigenpair(idx, v).real
        err = eps.computeError(idx, SLEPc.EPS.ErrorType.ABSOLUTE) / norm
        rows.append((lam, err) + tuple(obs(v)))
        if want_vectors:  # this rank's rows only
            vecs.append(v.getArray(readonly=True).copy())
    obs.destroy()
    v.destroy()
    stage.pop()
    table = np.array(rows, dtype=float).reshape(-1, 5)
    order = np.argsort(table[:, 0], kind="stable")
    table = table[order]
    ok = table[:, 1] <= tol
    vectors = None
    if want_vectors:
        vectors = np.array(vecs).reshape(len(vecs), len(system.ids), system.d)[order][ok]
    log(f"{method}: {nconv} converged, {int(ok.sum())} accepted of {n_wanted} wanted")
    return Spectrum(
        eigenvalue=table[ok, 0], error=table[ok, 1], participation_ratio=table[ok, 2],
        eps_perp=table[ok, 3], eps_par=table[ok, 4], matrix=kind, method=method, tolerance=tol,
        norm=norm, n_requested=n_wanted, rejected_eigenvalue=table[~ok, 0],
        rejected_error=table[~ok, 1], vectors=vectors,
        vector_ids=np.asarray(system.ids) if want_vectors else None)
