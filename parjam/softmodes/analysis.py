"""The whole soft-mode analysis of one cut packing (Wyart et al. 2005, Sections II-III and the
Appendix): count (Sec. II), null-space basis (Eq. 3), extension and f(x) (Sec. III), trial modes
(Eq. rr) against Eq. (kkk) and the variational count.  Solver-free: it drives the modules of
:mod:`parjam.softmodes`."""

import time
from dataclasses import dataclass, field

import numpy as np

from parjam import env
from parjam.errors import ParjamError
from parjam.softmodes.basis import COLUMNS_DEFAULT, eq3_residual
from parjam.softmodes.counting import null_count, variational_count
from parjam.softmodes.cut import CutSystem, bound_to
from parjam.softmodes.linalg import columns_of, orthonormality_error
from parjam.softmodes.nullspace import null_basis
from parjam.softmodes.observables import (coordinate_from_plane, extended_basis,
                                          extended_fraction, gradient_bound, modulation,
                                          overlap_function, overlap_without_localised)
from parjam.softmodes.operators import relaxed_matrix, rigidity_matrix
from parjam.softmodes.trial import energies, omega_L2

PROGRESS_SECONDS = 60.0  # the null basis reports its column blocks at most once a minute


@dataclass(kw_only=True)
class SoftModes:
    """Everything ``parjam softmodes`` reports for one cut packing (replicated on every rank
    except ``cs``, this rank's share of the cut network, and ``V``, this rank's rows of the
    extended basis)."""

    cs: CutSystem
    count: int  # null-space dimension, translations included
    n_soft: int  # count - d: the basis size
    V: np.ndarray  # rows lo..hi-1 of the basis that diagonalises G (columns by ascending e)
    lo: int
    hi: int
    e: np.ndarray  # extension of each basis mode
    rayleigh: np.ndarray  # <dR|M_cut|dR> of the null vectors (round-off)
    gap: float  # first eigenvalue of M_cut above the null space (SLEPc), in units of k
    eq3: float  # max |(dR_j - dR_i) . n_ij| over basis and remaining contacts
    ortho: float  # max |V^T V - I|
    overlap: np.ndarray  # (nbins, 3): x/L, f, f without the trivially localised modes
    trial_energy: np.ndarray  # <dR*|M_uncut|dR*> per basis mode (nan where e ~ 0)
    modulated_energy: np.ndarray  # <g dR|M_uncut|g dR> = e * trial energy, bounded by
    #                               kappa z_max |grad g|^2 for every soft mode
    e0: float
    omega_L2: float  # Eq. (kkk) for e0
    grad2: float
    omega_t2: float  # mean trial energy of the q' modes with e > e0
    n_below: int  # eigenmodes of the uncut M with omega^2 <= 2 omega_t^2 (translations included)
    fractions: np.ndarray  # (k, 2): e0, q'/q
    solver: dict = field(default_factory=dict)

    @property
    def q_prime(self):
        return int(np.count_nonzero(self.e > self.e0))

    @property
    def c_bound(self):
        """Lower bound of f (the paper's c ~ 0.6 in 3D)."""
        return float(self.overlap[:, 1].min())

    @property
    def c_nontrivial(self):
        """Lower bound of f once the trivially localised modes are projected out."""
        return float(self.overlap[:, 2].min())

    def basis_block(self, start, block):
        """(particle ids, modes start.. start + block of this rank's rows of the basis as
        (modes, particles, d)): what the file's /softmodes/basis holds of this rank."""
        cols = columns_of(self.V, start, min(start + block, self.n_soft))
        return self.cs.ids, cols.T.reshape(cols.shape[1], self.cs.n_local, self.cs.d)

    def summary(self):
        cs = self.cs
        ext = self.e > self.e0
        return {
            "N_active": cs.n, "Nc": cs.n_contacts, "excess": cs.excess, "q": cs.q,
            "count": self.count, "expected": cs.expected if cs.isostatic else None,
            "trivial": cs.trivial, "localised": cs.localised, "n_soft": self.n_soft,
            "gap": self.gap, "eq3_residual": self.eq3, "orthonormality": self.ortho,
            "e0": self.e0, "q_prime": self.q_prime, "q_prime_over_q": self.q_prime / cs.q,
            "c": self.c_bound, "c_nontrivial": self.c_nontrivial, "omega_L2": self.omega_L2,
            "trial_energy_max": float(np.max(self.trial_energy[ext])) if ext.any() else None,
            "omega_t2": self.omega_t2, "n_below_2omega_t2": self.n_below,
            "mean_modulated_energy": float(np.mean(self.modulated_energy)),
            "variational_ok": bool(self.n_below >= 0.5 * self.q_prime),
        }


def analyze(comm, cs, e0=0.1, nbins=10, progress=None, basis="block",
            columns=COLUMNS_DEFAULT, scratch=None):
    """Count, extract and characterise the soft modes of the cut system ``cs`` (made on
    ``comm``'s ranks; one prepared from a packing on another communicator is cut again on
    ``comm``, :func:`parjam.softmodes.cut.bound_to`); ``basis``
    chooses the null-space method and ``columns`` its column blocks (None: one block,
    :func:`parjam.softmodes.nullspace.null_basis`).  ``scratch``: a
    :class:`parjam.softmodes.scratch.ScratchSpace` (from :func:`scratch_space`) keeps the basis
    on disk there; the result's ``V`` is then a scratch basis, valid until the space closes."""
    PETSc = env.petsc()
    log = progress or (lambda msg: None)
    cs = bound_to(cs, comm)
    d = cs.d
    scale = cs.scale
    times = {}
    t0 = time.perf_counter()
    stage = PETSc.Log.Stage("softmodes: count")
    stage.push()
    Ms = relaxed_matrix(comm, cs, cs.kept, fmt="sbaij")  # the inertia's format, no conversion
    try:
        count = null_count(comm, Ms, scale)
    finally:
        Ms.destroy()
    stage.pop()
    times["count"] = time.perf_counter() - t0
    log(f"null space of the cut system: {count} (expected d + q - 1 = {cs.expected} "
        f"if isostatic), {cs.localised} trivially localised")
    n_soft = count - d
    if n_soft <= 0:
        raise ParjamError(f"the cut system has no soft mode besides the {d} translations "
                          f"(q = {cs.q} cuts on a packing {cs.excess:+d} from isostatic)")
    t0 = time.perf_counter()
    stage = PETSc.Log.Stage("softmodes: null space")
    stage.push()
    M = relaxed_matrix(comm, cs, cs.kept)
    nb = null_basis(comm, M, d, n_soft, scale, basis, columns,
                    store=None if scratch is None else scratch.basis,
                    progress=block_progress(log, n_soft))
    S = rigidity_matrix(comm, cs, cs.kept)
    eq3 = eq3_residual(comm, S, nb.V)
    S.destroy()
    M.destroy()
    stage.pop()
    times["null_space"] = time.perf_counter() - t0
    log(f"{n_soft} soft modes ({nb.solver}, {nb.iterations} iterations), "
        f"Eq. 3 residual {eq3:.1e}")
    t0 = time.perf_counter()
    stage = PETSc.Log.Stage("softmodes: analysis")
    stage.push()
    res = characterise(comm, cs, nb, count, e0, nbins)
    stage.pop()
    times["analysis"] = time.perf_counter() - t0
    res.eq3 = eq3
    res.solver = {"eps_type": nb.solver, "iterations": nb.iterations, "scale_k": scale,
                  "columns": int(columns) if columns is not None else 0,
                  "out_of_core": scratch is not None,
                  **{f"seconds_{k}": v for k, v in times.items()}}
    return res


def block_progress(log, n_soft, every=PROGRESS_SECONDS):
    """A progress callback for the column blocks of the null basis: one line per ``every``
    seconds at most (a cut at N = 1e5 spends an hour there)."""
    t0 = last = time.perf_counter()

    def report(found):
        nonlocal last
        now = time.perf_counter()
        if now - last >= every and found < n_soft:
            last = now
            log(f"null space: {found} of {n_soft} soft modes ({now - t0:.0f} s)")
    return report


def characterise(comm, cs, nb, count, e0, nbins):
    """Extension, f(x) and trial modes of the null basis ``nb`` (rotated in place: ``nb.V`` is
    the extended basis afterwards; no second n x n_soft array is made)."""
    assert (nb.lo, nb.hi) == (cs.lo, cs.hi)
    pos = cs.pos  # the owned active rows
    g = modulation(pos, cs.L, cs.planes)
    ortho = orthonormality_error(comm, nb.V)
    u = coordinate_from_plane(pos, cs.L, cs.planes[0])
    centres, f = overlap_function(comm, nb.V, u, nbins)  # basis-independent
    _, f_nt = overlap_without_localised(comm, cs, nb.V, nb.lo, nb.hi, u, nbins)
    e, V = extended_basis(comm, nb.V, g**2, inplace=True)  # Appendix
    Mu = relaxed_matrix(comm, cs, cs.contacts)
    Eg = energies(comm, Mu, V, weight=np.repeat(g, cs.d))  # <g dR|M|g dR>
    E = np.where(e > 1e-12, Eg / np.maximum(e, 1e-12), np.nan)  # Eq. (rr), C_b = e_b^-1/2
    grad2 = gradient_bound(cs.L, cs.planes)
    ext = e > e0
    omega_t2 = float(np.mean(E[ext])) if ext.any() else 0.0
    Mu.destroy()
    n_below = 0
    if ext.any():
        Ms = relaxed_matrix(comm, cs, cs.contacts, fmt="sbaij")
        try:
            n_below = variational_count(comm, Ms, omega_t2)
        finally:
            Ms.destroy()
    scale = cs.scale
    return SoftModes(cs=cs, count=count, n_soft=count - cs.d, V=V, lo=nb.lo, hi=nb.hi, e=e,
                     rayleigh=nb.rayleigh, gap=nb.gap / scale, eq3=0.0, ortho=ortho,
                     overlap=np.stack([centres, f, f_nt], axis=1), trial_energy=E,
                     modulated_energy=Eg, e0=e0, omega_L2=omega_L2(e0, cs.kappa, cs.z_max, grad2),
                     grad2=grad2, omega_t2=omega_t2, n_below=n_below,
                     fractions=extended_fraction(e, cs.q))
