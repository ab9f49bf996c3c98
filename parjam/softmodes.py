"""Soft modes after plane cuts (Wyart, Silbert, Nagel & Witten, PRE 72, 051306, Sections II-III
and the Appendix): cut the contacts crossing planes, extract the null space of the rigidity
matrix, measure how extended it is, and build the anomalous trial modes.

Pipeline (every step distributed over the ranks of ``comm``; rows split as in
:func:`parjam.hessian.row_range`, one particle per block of d rows):

1. :func:`prepare` removes rattlers, re-indexes the N' non-rattlers, checks isostaticity
   (Nc = Nc_iso = d(N' - 1) + 1) and cuts every contact whose minimum-image bond crosses one of
   the planes (:func:`crossing`; bonds wrapping across the box edge count for a plane at 0).
2. The relaxed-spring matrix of the remaining contacts, M = S^T K S (Eq. 1 without the stress
   term), has the same null space as the rigidity matrix S of Eq. 3.  Its dimension is counted
   exactly with MUMPS inertia at two thresholds (:func:`count_below`, the gap must separate
   them) and compared with q + d - 1 (isostatic: the q cuts open q floppy modes, the first one
   also kills the packing's single self-stress, plus the d translations).
3. The basis orthogonal to the d global translations (the "trivial" modes, deflated) comes from
   block inverse iteration with one MUMPS factor of M + tau I, tau = 1e-8 k, and a
   Rayleigh-Ritz step (:func:`null_basis_block`), or from SLEPc shift-and-invert
   (:func:`null_basis_krylov`); each vector is checked against Eq. 3 on the remaining contacts
   (:func:`eq3_residual`), and the gap above the null space comes from the same factor.
4. Extension e = sum_i g_i^2 |dR_i|^2, g the sine modulation that vanishes on the planes
   (:func:`modulation`; g = sin(pi x / L) for one plane, x measured from it).  The Appendix's
   extended subspace (remove the mode of smallest <dR|G|dR> until all exceed e0) is the
   eigen-decomposition of G projected on the soft space (:func:`extended_basis`).
5. f(x) from the trace of the soft-space projector (:func:`overlap_function`), and the trial
   modes dR*_b = g dR_b / sqrt(e_b) (Eq. rr), orthonormal by construction, with energies
   <dR*|M_uncut|dR*> bounded by omega_L^2 = kappa z_max (pi/L)^2 / e0 (Eq. kkk).

Why one file of ~1000 lines: the five steps share the distributed row layout, the cut system
(:class:`CutSystem`) and the MUMPS factor of step 3, and are read in that order against the
paper; split, every module would import every other.  Its sections are marked by ``# ---``
rules (cuts, matrices, counting, extraction, checks, extension, f(x), trial modes, dense
references, the whole analysis, output).
"""

import re
import time
from dataclasses import dataclass, field

import numpy as np

from parjam import env, factor, hessian, io, network, potential, spectrum
from parjam.errors import ParjamError
from parjam.network import Contacts

AXES = "xyz"
E0_LADDER = (0.05, 0.1, 0.2, 0.3, 0.4)


# --------------------------------------------------------------------------- planes and cuts

@dataclass(frozen=True, order=True)
class Plane:
    """The plane x_axis = frac * L."""

    axis: int
    frac: float

    @property
    def label(self):
        return f"{AXES[self.axis]}={self.frac:g}"


def parse_cut(text, d):
    """``"x=0.5"`` -> Plane(0, 0.5); the position is a fraction of the box edge in [0, 1)."""
    m = re.fullmatch(r"\s*([xyzXYZ])\s*=\s*([-+0-9.eE]+)\s*", text)
    if not m:
        raise ParjamError(f"--cut {text!r}: expected AXIS=FRACTION, e.g. x=0.5")
    axis = AXES.index(m.group(1).lower())
    try:
        frac = float(m.group(2))
    except ValueError:
        raise ParjamError(f"--cut {text!r}: {m.group(2)!r} is not a number") from None
    if axis >= d:
        raise ParjamError(f"--cut {text!r}: a {d}D packing has no {AXES[axis]} axis")
    if not (np.isfinite(frac) and 0.0 <= frac < 1.0):
        raise ParjamError(f"--cut {text!r}: the position must be a fraction of the box edge in "
                          f"[0, 1), got {frac}")
    return Plane(axis, frac)


def subdivision_planes(m, d):
    """The planes x_a = k L / m (k = 0..m-1) in every direction: the m^d sub-boxes (Sec. III)."""
    if m < 1:
        raise ParjamError(f"--subdivide must be >= 1, got {m}")
    return [Plane(a, k / m) for a in range(d) for k in range(m)]


def crossing(x_i, r_a, L, x0):
    """Mask of bonds x_i -> x_i + r_a that cross the plane x = x0 (or a periodic image of it).

    The bond crosses when its two ends lie in different periods of (x - x0) / L; |r_a| < L / 2
    (minimum image) so a bond crosses at most once.  A plane at 0 catches the bonds that wrap
    across the box edge.
    """
    return np.floor((x_i - x0) / L) != np.floor((x_i + r_a - x0) / L)


def cut_masks(pos, contacts, L, planes):
    """One mask per plane over ``contacts`` (i < j, r_ij = x_j - x_i minimum image)."""
    return [crossing(pos[contacts.i, p.axis], contacts.rij[:, p.axis], L, p.frac * L)
            for p in planes]


def _reindexed(c, index):
    return Contacts(index[c.i], index[c.j], c.rij, c.r, c.sigma)


@dataclass
class CutSystem:
    """The non-rattlers of a packing, their contacts, and the split into kept and cut ones.

    Particle indices in ``contacts``, ``kept`` and ``cut`` run over 0..n-1 (non-rattlers of the
    uncut packing, in their original order); ``original`` maps them back to the packing.
    """

    d: int
    L: float
    alpha: float
    eps: float
    pos: np.ndarray  # (n, d) positions of the non-rattlers
    original: np.ndarray  # (n,) their indices in the packing
    contacts: Contacts  # all contacts among non-rattlers (the uncut network)
    is_cut: np.ndarray  # mask over ``contacts``
    planes: list
    excess: int  # Nc - Nc_iso of the uncut network
    n_total: int  # particles in the packing, rattlers included
    per_plane: list = field(default_factory=list)  # q of each plane (a contact may count twice)

    @property
    def n(self):
        return len(self.pos)

    @property
    def kept(self):
        return self.contacts.subset(~self.is_cut)

    @property
    def cut(self):
        return self.contacts.subset(self.is_cut)

    @property
    def q(self):
        return int(self.is_cut.sum())

    @property
    def isostatic(self):
        return self.excess == 0

    @property
    def trivial(self):
        """The d global translations."""
        return self.d

    @property
    def expected(self):
        """Null-space dimension of an isostatic packing after q cuts: the d translations plus
        q - 1 floppy modes (the first cut removes the single self-stress instead)."""
        return self.d + self.q - 1

    def degree(self, kept=True):
        c = self.kept if kept else self.contacts
        return np.bincount(c.i, minlength=self.n) + np.bincount(c.j, minlength=self.n)

    @property
    def localised_particles(self):
        """Particles left with fewer than d contacts: each has d - z_i trivially localised modes
        (it moves alone, perpendicular to its remaining contacts)."""
        return np.flatnonzero(self.degree() < self.d)

    @property
    def localised(self):
        z = self.degree()
        return int(np.maximum(self.d - z, 0).sum())

    @property
    def z_max(self):
        return int(self.degree(kept=False).max())

    @property
    def kappa(self):
        """max_contacts V''(r) r^2: 1 in the paper's units (harmonic, k sigma^2 = 1, r < sigma)."""
        c = self.contacts
        return float((potential.d2V(c.r, c.sigma, self.alpha, self.eps) * c.r**2).max())

    def cut_original(self):
        """The q removed contacts as (i, j) pairs of the packing's particle indices."""
        c = self.cut
        return np.stack([self.original[c.i], self.original[c.j]], axis=1).reshape(-1, 2)


def prepare(pack, planes, allow_hyperstatic=False, net=None):
    """Remove rattlers, check isostaticity and cut the contacts crossing ``planes``."""
    if not planes:
        raise ParjamError("no cut given: use --cut AXIS=FRACTION and/or --subdivide M")
    net = net if net is not None else network.analyze(pack)
    if net.n_active == 0:
        raise ParjamError(f"all {pack.n} particles are rattlers: not a jammed packing, "
                          "there is no contact network to cut")
    if net.excess != 0 and not allow_hyperstatic:
        kind = "hyperstatic" if net.excess > 0 else "hypostatic"
        raise ParjamError(
            f"the packing is not isostatic: Nc = {net.n_contacts} contacts among N' = "
            f"{net.n_active} non-rattlers, Nc_iso = d(N'-1)+1 = {net.n_iso} ({kind} by "
            f"{net.excess:+d}; dphi too large?). The soft-mode count d + q - 1 needs an "
            "isostatic packing (dphi -> 0); pass --allow-hyperstatic to analyse it anyway")
    active = ~net.rattler
    index = np.cumsum(active) - 1
    contacts = _reindexed(net.contacts, index)
    masks = cut_masks(pack.pos, net.contacts, pack.L, planes)
    for p, m in zip(planes, masks):
        if not m.any():
            raise ParjamError(f"the plane {p.label} cuts no contact among the {net.n_active} "
                              "non-rattlers: nothing to analyse (is the packing jammed?)")
    return CutSystem(pack.d, pack.L, pack.alpha, pack.eps, pack.pos[active],
                     np.flatnonzero(active), contacts, np.logical_or.reduce(masks),
                     list(planes), net.excess, pack.n, [int(m.sum()) for m in masks])


# --------------------------------------------------------------------------- matrices

def _owned(c, lo, hi):
    """Contacts with at least one endpoint among this rank's particles [lo, hi)."""
    return ((c.i >= lo) & (c.i < hi)) | ((c.j >= lo) & (c.j < hi))


def relaxed_matrix(comm, cs, contacts):
    """Distributed relaxed-spring matrix M = sum_c k_c n n^T (Eq. 1 without the stress term,
    = S^T K S) of ``contacts`` over the n non-rattlers."""
    lo, hi = hessian.row_range(cs.n, comm)
    c = contacts.subset(_owned(contacts, lo, hi))
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, cs.alpha, cs.eps, kind="relaxed")
    return hessian.assemble(comm, cs.n, cs.d, c.i, c.j, blocks)


def rigidity_matrix(comm, cs, contacts):
    """Distributed rigidity matrix S (Nc x dN'): row c is (dR_j - dR_i) . n_ij (Eq. 3).

    Contact rows are split evenly over the ranks; the columns follow the row layout of M, so S
    multiplies the basis vectors directly.
    """
    PETSc = env.petsc()
    nc, d = len(contacts), cs.d
    lo_c, hi_c = hessian.row_range(nc, comm) if nc else (0, 0)
    lo, hi = hessian.row_range(cs.n, comm)
    i, j = contacts.i[lo_c:hi_c], contacts.j[lo_c:hi_c]
    n = contacts.rij[lo_c:hi_c] / contacts.r[lo_c:hi_c, None]
    a, b = np.minimum(i, j), np.maximum(i, j)
    sign_a = np.where(a == i, -1.0, 1.0)[:, None]  # -n on particle i, +n on particle j
    cols = np.concatenate([a[:, None] * d + np.arange(d), b[:, None] * d + np.arange(d)], axis=1)
    vals = np.concatenate([sign_a * n, -sign_a * n], axis=1)
    indptr = np.arange(0, 2 * d * len(i) + 1, 2 * d, dtype=PETSc.IntType)
    S = PETSc.Mat().createAIJ(((hi_c - lo_c, nc), ((hi - lo) * d, cs.n * d)),
                              csr=(indptr, cols.ravel().astype(PETSc.IntType), vals.ravel()),
                              comm=comm)
    return S


def translation_columns(M, d):
    """The d normalised translations as this rank's rows of an array (one column each)."""
    vecs = translations(M, d)
    T = np.stack([v.getArray().copy() for v in vecs], axis=1)
    for v in vecs:
        v.destroy()
    return T


def translations(M, d):
    """The d unit translations as Vecs in the layout of M (normalised)."""
    out = []
    n = M.getSize()[0] // d
    for a in range(d):
        v = M.createVecRight()
        lo, hi = v.getOwnershipRange()
        arr = np.zeros(hi - lo)
        arr[(np.arange(lo, hi) % d) == a] = 1.0 / np.sqrt(n)
        v.setArray(arr)
        out.append(v)
    return out


# --------------------------------------------------------------------------- counting

def count_below(comm, M, s, prefix="soft_inertia_"):
    """Number of eigenvalues of the symmetric M below s: the negative inertia of M - s I from a
    MUMPS LDL^T factorisation (SBAIJ; ICNTL(13) = 1 makes the inertia exact on several ranks)."""
    PETSc = env.petsc()
    A = M.copy()
    A.shift(-s)
    A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
    As = A.convert("sbaij")
    pc = PETSc.PC().create(comm=comm)
    try:
        pc.setOptionsPrefix(prefix)
        pc.setOperators(As)
        factor.use_cholesky(pc)
        factor.exact_inertia(pc, null_pivots=True)
        pc.setFromOptions()
        pc.setUp()
        neg, zero, _ = pc.getFactorMatrix().getInertia()
    finally:
        pc.destroy()
        As.destroy()
        A.destroy()
    return int(neg) + int(zero)


def stiffness_scale(contacts, alpha, eps):
    """Mean contact stiffness k = V''(r): the unit in which the thresholds below are set."""
    return float(np.mean(potential.d2V(contacts.r, contacts.sigma, alpha, eps)))


def null_count(comm, M, scale, thresholds=(1e-10, 1e-6)):
    """Null-space dimension of the PSD matrix M: eigenvalues below t * scale, counted by inertia
    at both thresholds; a different count means no clear gap (ParjamError)."""
    counts = [count_below(comm, M, t * scale) for t in thresholds]
    if counts[0] != counts[1]:
        raise ParjamError(
            f"no spectral gap around zero: {counts[0]} eigenvalues below {thresholds[0]:g} k "
            f"but {counts[1]} below {thresholds[1]:g} k; the null space is ill-defined "
            "(nearly floppy contacts?)")
    return counts[0]


# --------------------------------------------------------------------------- extraction

@dataclass
class NullBasis:
    """An orthonormal basis of the null space orthogonal to the translations.

    ``V`` holds this rank's rows (particles lo..hi-1, d rows each) of the n_soft columns;
    ``rayleigh`` the eigenvalues of M for them (round-off), ``gap`` the next eigenvalue found.
    """

    V: np.ndarray
    rayleigh: np.ndarray
    gap: float
    lo: int
    hi: int
    iterations: int
    solver: str


BASIS_METHODS = ("block", "krylov")


def null_basis(comm, M, d, n_soft, scale, method="block"):
    """The n_soft null vectors of M orthogonal to the d translations (a :class:`NullBasis`), by
    block inverse iteration (``block``, the default; much faster for hundreds of modes, see
    docs/bench-softmodes.md) or by SLEPc Krylov-Schur shift-and-invert (``krylov``)."""
    if method == "block":
        return null_basis_block(comm, M, d, n_soft, scale)
    if method == "krylov":
        return null_basis_krylov(comm, M, d, n_soft, scale)
    raise ParjamError(f"unknown basis method {method!r} (choose from {', '.join(BASIS_METHODS)})")


def null_basis_krylov(comm, M, d, n_soft, scale, prefix="soft_", margin=4, tol=1e-12):
    """The n_soft null vectors of M orthogonal to the d translations, by SLEPc shift-and-invert
    (Krylov-Schur, target -tau = -1e-8 k, MUMPS Cholesky of M + tau I, translations deflated).

    The null space is exactly degenerate: a single-vector Krylov method picks it up a few
    vectors per restart.  A target far below the gap and keeping 80% of the basis at each
    restart cut the factor solves from ~5.3 to ~2.4 per soft mode (N = 1024 in 3D).

    ``margin`` extra eigenpairs show the gap above the null space.  Options under ``prefix``
    (``-soft_eps_*``, ``-soft_st_*``) override the defaults.
    """
    PETSc, SLEPc = env.petsc(), env.slepc()
    nev = n_soft + max(0, min(margin, M.getSize()[0] - d - n_soft))  # room left for the gap
    eps = SLEPc.EPS().create(comm=comm)
    try:
        try:
            _configure_eps(eps, M, d, nev, scale, prefix, tol)
            eps.solve()
        except PETSc.Error as exc:
            raise ParjamError(f"SLEPc could not compute the soft modes (PETSc error "
                              f"{exc.ierr}; see the messages above; check the -{prefix}eps_* "
                              f"and -{prefix}st_* options)") from None
        nconv = eps.getConverged()
        if nconv < n_soft:
            raise ParjamError(f"SLEPc found {nconv} of the {n_soft} soft modes (raise "
                              f"-{prefix}eps_max_it or -{prefix}eps_ncv)", collective=True)
        V, lam = _eigenvectors(eps, M, n_soft)
        if lam.max() > 1e-6 * scale:
            raise ParjamError(f"SLEPc returned a vector with eigenvalue {lam.max():.2e} among "
                              f"the {n_soft} soft modes (the inertia count): a null vector was "
                              f"missed; raise -{prefix}eps_ncv or -{prefix}eps_mpd")
        gap = eps.getEigenvalue(n_soft).real if nconv > n_soft else np.inf
        lo, hi = M.getOwnershipRange()
        return NullBasis(V, lam, float(gap), lo // d, hi // d, eps.getIterationNumber(),
                         eps.getType())
    finally:
        eps.destroy()


def _configure_eps(eps, M, d, nev, scale, prefix, tol):
    SLEPc = env.slepc()
    eps.setOperators(M)
    eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
    eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
    eps.setKrylovSchurRestart(0.8)  # keep more of the degenerate null cluster per restart
    mpd = nev if nev <= 256 else 256
    eps.setDimensions(nev, env.petsc().DECIDE, mpd)
    eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
    eps.setTarget(-1e-8 * scale)
    eps.setConvergenceTest(SLEPc.EPS.Conv.ABS)
    eps.setTolerances(tol * scale, 1000)
    spectrum.configure_sinvert(eps)
    vecs = translations(M, d)
    eps.setDeflationSpace(vecs)  # SLEPc keeps its own copy
    for v in vecs:
        v.destroy()
    eps.setOptionsPrefix(prefix)
    eps.setFromOptions()


def _eigenvectors(eps, M, k):
    """The first k eigenvectors (local rows, as columns) and their eigenvalues, ascending."""
    v = M.createVecRight()
    lo, hi = v.getOwnershipRange()
    V = np.empty((hi - lo, k))
    lam = np.empty(k)
    for b in range(k):
        lam[b] = eps.getEigenpair(b, v).real
        V[:, b] = v.getArray()
    v.destroy()
    order = np.argsort(lam, kind="stable")
    return V[:, order], lam[order]


# --------------------------------------------------------------------------- block extraction

def null_basis_block(comm, M, d, n_soft, scale, prefix="soft_", oversample=8, tau=1e-8,
                     tol=1e-12, passes=3, max_rounds=5, block=512, seed=0):
    """The n_soft null vectors of M orthogonal to the d translations, by block inverse
    (subspace) iteration with one MUMPS Cholesky factor of A = M + tau k I.

    Every null vector is amplified by 1/tau per solve, the rest by at most 1/(gap + tau): at
    tau = 1e-8 k and a gap of ~1e-5..1e-3 k (the inertia check proves >= 1e-6 k), ``passes``
    solves of n_soft + ``oversample`` right-hand sides leave a contamination of < 1e-9, and a
    Rayleigh-Ritz step on the result removes the rest.  The solves use MUMPS's multi-RHS path
    in blocks of ``block`` columns; the orthonormalisation and Rayleigh-Ritz are dense BLAS-3
    on the local rows.  A Krylov method instead picks up the degenerate null cluster a few
    vectors per restart and orthogonalises every new vector against all the locked ones
    (docs/bench-softmodes.md compares the two).  ``-soft_ksp_*``/``-soft_pc_*`` options reach
    the factorisation, ``-soft_gap_eps_*`` the gap solve.
    """
    lo, hi = M.getOwnershipRange()
    k = min(n_soft + oversample, M.getSize()[0] - d)
    ksp = _factorised(comm, M, tau * scale, prefix)
    T = translation_columns(M, d)
    try:
        X = random_block(lo, hi, k, seed)
        for rnd in range(1, max_rounds + 1):
            for _ in range(passes if rnd == 1 else 1):
                X = _normalised_columns(comm, _apply_inverse(comm, ksp, _deflated(comm, T, X),
                                                             block))
            V, theta, res = _rayleigh_ritz(comm, M, _orthonormal(comm, _deflated(comm, T, X)))
            if V.shape[1] >= n_soft and res[:n_soft].max() <= tol * scale \
                    and theta[n_soft - 1] <= 1e-6 * scale:
                break
            if V.shape[1] < n_soft:
                raise ParjamError(f"block inverse iteration kept only {V.shape[1]} of the "
                                  f"{n_soft} null directions", collective=True)
            X = V
        else:
            raise ParjamError(f"block inverse iteration did not converge in {max_rounds} rounds "
                              f"(largest residual {res[:n_soft].max() / scale:.1e} k; try "
                              "--basis krylov)", collective=True)
        V = V[:, :n_soft]
        gap = gap_above(comm, ksp, np.concatenate([T, V], axis=1), tau * scale,
                        prefix + "gap_")
    finally:
        ksp.destroy()
    return NullBasis(V, theta[:n_soft], gap, lo // d, hi // d, passes + rnd - 1,
                     "block-inverse")


def _deflated(comm, T, X):
    """X with the columns of the orthonormal T projected out."""
    return X - T @ gram(comm, T, X)


def _normalised_columns(comm, X):
    norms = np.sqrt(allreduce(comm, (X * X).sum(axis=0)))
    return X / np.maximum(norms, np.finfo(float).tiny)


def _factorised(comm, M, shift, prefix):
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


def random_block(lo, hi, k, seed, rows=3072):
    """Gaussian rows lo..hi-1 of a global n x k matrix drawn in fixed row blocks, so that the
    start (and the result) does not depend on the number of ranks."""
    out = np.empty((hi - lo, k))
    for b in range(lo // rows, (hi - 1) // rows + 1 if hi > lo else lo // rows):
        block = np.random.default_rng([seed, b]).standard_normal((rows, k))
        a, z = max(lo, b * rows), min(hi, (b + 1) * rows)
        out[a - lo:z - lo] = block[a - b * rows:z - b * rows]
    return out


def _apply_inverse(comm, ksp, X, block):
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


def _orthonormal(comm, Y, passes=2, drop=1e-13):
    """An orthonormal basis of span(Y) by SVQB (eigendecomposition of the scaled Gram matrix),
    applied twice; directions weaker than ``drop`` relative to the strongest are dropped."""
    for _ in range(passes):
        G = gram(comm, Y)
        s = 1.0 / np.sqrt(np.maximum(np.diag(G), np.finfo(float).tiny))
        lam, W = np.linalg.eigh(G * s[:, None] * s[None, :])
        keep = lam > drop * lam.max()
        Y = (Y * s) @ (W[:, keep] / np.sqrt(lam[keep]))
    return Y


def _mat_apply(comm, M, X):
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


def _rayleigh_ritz(comm, M, Q):
    """Ritz vectors of M in span(Q) (orthonormal), ascending, and their residual norms."""
    MQ = _mat_apply(comm, M, Q)
    H = gram(comm, Q, MQ)
    theta, W = np.linalg.eigh(0.5 * (H + H.T))
    V, MV = Q @ W, MQ @ W
    res = np.sqrt(allreduce(comm, ((MV - V * theta) ** 2).sum(axis=0)))
    return V, theta, res


def gap_above(comm, ksp, U, shift, prefix="soft_gap_", tol=1e-8):
    """Lowest eigenvalue of M in the complement of the orthonormal columns U (translations and
    null basis): the largest eigenvalue 1 / (lambda + shift) of P A^-1 P, P = I - U U^T, by
    SLEPc Krylov-Schur on a shell operator that reuses the factor in ``ksp``."""
    PETSc, SLEPc = env.petsc(), env.slepc()
    A = ksp.getOperators()[0]
    if A.getSize()[0] - U.shape[1] <= 0:
        return np.inf
    op = PETSc.Mat().createPython(A.getSizes(), _ProjectedInverse(comm, ksp, U), comm=comm)
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


class _ProjectedInverse:
    """y = P A^-1 P x with P = I - U U^T (petsc4py shell-matrix context)."""

    def __init__(self, comm, ksp, U):
        self.comm, self.ksp, self.U = comm, ksp, U
        self.work = ksp.getOperators()[0].createVecRight()

    def _project(self, a):
        return a - self.U @ allreduce(self.comm, self.U.T @ a)

    def mult(self, mat, x, y):
        self.work.setArray(self._project(x.getArray(readonly=True)))
        self.ksp.solve(self.work, y)
        y.setArray(self._project(y.getArray(readonly=True)))


# --------------------------------------------------------------------------- checks

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


def orthonormality_error(comm, V):
    k = V.shape[1]
    return float(np.abs(gram(comm, V) - np.eye(k)).max()) if k else 0.0


def eq3_residual(comm, S, V):
    """max over basis vectors and remaining contacts of |(dR_j - dR_i) . n_ij| (Eq. 3)."""
    x, y = S.createVecs()
    worst = 0.0
    for b in range(V.shape[1]):
        x.setArray(V[:, b])
        S.mult(x, y)
        worst = max(worst, y.norm(env.petsc().NormType.INFINITY))
    x.destroy()
    y.destroy()
    return float(worst)


# --------------------------------------------------------------------------- extension

def modulation(pos, L, planes):
    """g_i of Eq. (rr): the product over cut directions of sin(pi u / l), u the distance from
    the previous plane along that axis and l the spacing to the next one (one plane: l = L,
    g = sin(pi x / L) with x measured from the plane).  g vanishes on every plane."""
    g = np.ones(len(pos))
    for axis, cuts in _planes_by_axis(planes).items():
        p = np.sort(cuts) * L
        u = np.mod(pos[:, axis] - p[0], L)
        starts = p - p[0]
        ends = np.append(starts[1:], L)
        k = np.searchsorted(starts, u, side="right") - 1
        g *= np.sin(np.pi * (u - starts[k]) / (ends[k] - starts[k]))
    return g


def _planes_by_axis(planes):
    out = {}
    for p in sorted(set(planes)):
        out.setdefault(p.axis, []).append(p.frac)
    return out


def gradient_bound(L, planes):
    """max |grad g|^2 <= sum over cut axes of (pi / l_min)^2, l_min the smallest spacing."""
    total = 0.0
    for cuts in _planes_by_axis(planes).values():
        p = np.sort(cuts) * L
        spacing = np.diff(np.append(p, p[0] + L)).min()
        total += (np.pi / spacing) ** 2
    return total


def omega_L2(e0, kappa, z_max, grad2):
    """Eq. (kkk): omega_L^2 = e0^-1 (pi/L)^2 z_max, with (pi/L)^2 -> max|grad g|^2 for several
    planes and the stiffness factor kappa = max k r^2 (1 for harmonic contacts)."""
    return kappa * z_max * grad2 / e0


def extension(comm, V, g2):
    """e_b = sum_i g_i^2 |dR_i,b|^2 of each (normalised) column; g2 per local particle."""
    d = V.shape[0] // max(len(g2), 1) if len(g2) else 1
    w = np.repeat(g2, d)
    return allreduce(comm, (w[:, None] * V * V).sum(axis=0))


def extended_basis(comm, V, g2):
    """Rotate the soft basis so that G (g_i^2 on particle i) is diagonal within it.

    The Appendix removes, one at a time, the remaining mode with the smallest <dR|G|dR>: that
    is the lowest eigenvector of G projected on the remaining space, so the procedure peels off
    the eigenvectors of P G P in ascending order and q' = #{e_b > e0}.  Returns (e ascending,
    rotated local rows)."""
    d = V.shape[0] // max(len(g2), 1) if len(g2) else 1
    w = np.repeat(g2, d)
    A = gram(comm, V, w[:, None] * V)
    A = comm.tompi4py().bcast(0.5 * (A + A.T), root=0)  # identical on every rank
    e, U = np.linalg.eigh(A)
    return e, V @ U


def extended_fraction(e, q, e0s=E0_LADDER):
    """q'/q for each e0: the number of modes of the extended subspace (e > e0) per cut."""
    return np.array([[e0, np.count_nonzero(e > e0) / q] for e0 in e0s])


def peel_extended(A, e0):
    """The Appendix's procedure done literally on a small dense projected G (for checks):
    repeatedly drop the direction of smallest <dR|G|dR> in the remaining space."""
    Q = np.eye(len(A))
    while Q.shape[1]:
        a, U = np.linalg.eigh(Q.T @ A @ Q)
        if a[0] > e0:
            break
        Q = Q @ U[:, 1:]
    return Q.shape[1]


# --------------------------------------------------------------------------- f(x)

def overlap_function(comm, V, u, nbins):
    """f(u) on u = x/L in [0, 1) (x measured from the first plane along its axis): the trace of
    the soft-space projector per slab, sum_b sum_{i in slab} |dR_i,b|^2 / (n_modes du).

    This is the paper's q^-1 sum_b ... rescaled by L (f_paper L), normalised by the number of
    modes so that its integral is 1; it is independent of the basis chosen.
    """
    k = V.shape[1]
    d = V.shape[0] // max(len(u), 1) if len(u) else 1
    diag = (V * V).reshape(len(u), d, k).sum(axis=(1, 2))
    hist = np.bincount(np.minimum((u * nbins).astype(int), nbins - 1), weights=diag,
                       minlength=nbins)
    hist = allreduce(comm, hist)
    centres = (np.arange(nbins) + 0.5) / nbins
    return centres, hist * nbins / max(k, 1)


def localised_vectors(cs):
    """The trivially localised modes: for each particle left with z_i < d contacts, an
    orthonormal basis of the directions perpendicular to its remaining contact normals, as
    (particle, d-vector) pairs (same list on every rank)."""
    kept = cs.kept
    out = []
    for p in cs.localised_particles:
        mine = (kept.i == p) | (kept.j == p)
        normals = kept.rij[mine] / kept.r[mine, None]
        _, sv, Wt = np.linalg.svd(normals.reshape(-1, cs.d), full_matrices=True)
        rank = int(np.count_nonzero(sv > 1e-10))
        out += [(int(p), w) for w in Wt[rank:]]
    return out


def without_localised(comm, cs, V, lo, hi):
    """An orthonormal basis (local rows) of the soft space with the trivially localised modes
    projected out: span(V, translations) minus span(localised, translations)."""
    d = cs.d
    loc = localised_vectors(cs)
    Z = np.zeros(((hi - lo) * d, len(loc) + d))
    for k, (p, w) in enumerate(loc):
        if lo <= p < hi:
            Z[(p - lo) * d:(p - lo + 1) * d, k] = w
    for a in range(d):
        Z[a::d, len(loc) + a] = 1.0 / np.sqrt(cs.n)
    R = np.linalg.cholesky(gram(comm, Z)).T
    Q = np.linalg.solve(R.T, Z.T).T  # Z R^-1: orthonormal
    Vp = V - Q @ gram(comm, Q, V)
    lam, U = np.linalg.eigh(comm.tompi4py().bcast(gram(comm, Vp), root=0))
    keep = lam > 0.5
    return Vp @ (U[:, keep] / np.sqrt(lam[keep]))


def coordinate_from_plane(pos, L, plane):
    return np.mod(pos[:, plane.axis] / L - plane.frac, 1.0)


# --------------------------------------------------------------------------- trial modes

def trial_modes(V, g, e, floor=1e-12):
    """Eq. (rr): dR*_b = C_b g dR_b with C_b = e_b^-1/2 (orthonormal because G is diagonal in
    the rotated basis V); columns with e_b < floor are left at zero."""
    d = V.shape[0] // max(len(g), 1) if len(g) else 1
    C = np.where(e > floor, 1.0 / np.sqrt(np.maximum(e, floor)), 0.0)
    return np.repeat(g, d)[:, None] * V * C[None, :]


def energies(comm, M, T, projected=False, weight=None):
    """<t|M|t> per column t of T (local rows), or of weight * T without storing that product;
    with ``projected`` also T^T M T."""
    x, y = M.createVecs()
    MT = np.empty_like(T) if projected else None
    E = np.empty(T.shape[1])
    for b in range(T.shape[1]):
        t = T[:, b] if weight is None else weight * T[:, b]
        x.setArray(t)
        M.mult(x, y)
        E[b] = t @ y.getArray()
        if projected:
            MT[:, b] = y.getArray()
    x.destroy()
    y.destroy()
    E = allreduce(comm, E)
    if not projected:
        return E
    return E, gram(comm, T if weight is None else weight[:, None] * T, MT)


def variational_count(comm, M_uncut, omega_t2):
    """Number of true eigenmodes of the uncut M with omega^2 < 2 omega_t^2 (inertia)."""
    return count_below(comm, M_uncut, 2.0 * omega_t2)


# --------------------------------------------------------------------------- dense references

def dense_rigidity(cs, contacts):
    """Dense S (Nc x dN') of Eq. 3 for small systems."""
    n = contacts.rij / contacts.r[:, None]
    S = np.zeros((len(contacts), cs.n, cs.d))
    rows = np.arange(len(contacts))
    S[rows, contacts.i] -= n
    S[rows, contacts.j] += n
    return S.reshape(len(contacts), cs.n * cs.d)


def dense_null_space(S, rtol=1e-8):
    """(dimension, orthonormal basis, singular values) of the null space of S by dense SVD."""
    _, s, Vt = np.linalg.svd(S, full_matrices=True)
    rank = int(np.count_nonzero(s > rtol * s[0])) if len(s) else 0
    return S.shape[1] - rank, Vt[rank:].T, s


# --------------------------------------------------------------------------- the whole analysis

@dataclass(kw_only=True)
class SoftModes:
    """Everything ``parjam softmodes`` reports for one cut packing (replicated on every rank
    except ``V``, this rank's rows of the extended basis)."""

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

    def summary(self):
        cs = self.cs
        ext = self.e > self.e0
        return {
            "N_active": cs.n, "Nc": len(cs.contacts), "excess": cs.excess, "q": cs.q,
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


def analyze(comm, cs, e0=0.1, nbins=10, progress=None, basis="block"):
    """Count, extract and characterise the soft modes of the cut system ``cs``; ``basis``
    chooses the null-space method (:func:`null_basis`)."""
    PETSc = env.petsc()
    log = progress or (lambda msg: None)
    d = cs.d
    scale = stiffness_scale(cs.kept, cs.alpha, cs.eps)
    times = {}
    t0 = time.perf_counter()
    stage = PETSc.Log.Stage("softmodes: count")
    stage.push()
    M = relaxed_matrix(comm, cs, cs.kept)
    count = null_count(comm, M, scale)
    stage.pop()
    times["count"] = time.perf_counter() - t0
    log(f"null space of the cut system: {count} (expected d + q - 1 = {cs.expected} "
        f"if isostatic), {cs.localised} trivially localised")
    n_soft = count - d
    if n_soft <= 0:
        M.destroy()
        raise ParjamError(f"the cut system has no soft mode besides the {d} translations "
                          f"(q = {cs.q} cuts on a packing {cs.excess:+d} from isostatic)")
    t0 = time.perf_counter()
    stage = PETSc.Log.Stage("softmodes: null space")
    stage.push()
    nb = null_basis(comm, M, d, n_soft, scale, basis)
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
    res = _characterise(comm, cs, nb, count, e0, nbins)
    stage.pop()
    times["analysis"] = time.perf_counter() - t0
    res.eq3 = eq3
    res.solver = {"eps_type": nb.solver, "iterations": nb.iterations, "scale_k": scale,
                  **{f"seconds_{k}": v for k, v in times.items()}}
    return res


def _characterise(comm, cs, nb, count, e0, nbins):
    pos = cs.pos[nb.lo:nb.hi]
    g = modulation(pos, cs.L, cs.planes)
    ortho = orthonormality_error(comm, nb.V)
    e, V = extended_basis(comm, nb.V, g**2)
    u = coordinate_from_plane(pos, cs.L, cs.planes[0])
    centres, f = overlap_function(comm, V, u, nbins)
    _, f_nt = overlap_function(comm, without_localised(comm, cs, V, nb.lo, nb.hi), u, nbins)
    Mu = relaxed_matrix(comm, cs, cs.contacts)
    Eg = energies(comm, Mu, V, weight=np.repeat(g, cs.d))  # <g dR|M|g dR>
    E = np.where(e > 1e-12, Eg / np.maximum(e, 1e-12), np.nan)  # Eq. (rr), C_b = e_b^-1/2
    grad2 = gradient_bound(cs.L, cs.planes)
    ext = e > e0
    omega_t2 = float(np.mean(E[ext])) if ext.any() else 0.0
    n_below = variational_count(comm, Mu, omega_t2) if ext.any() else 0
    Mu.destroy()
    scale = stiffness_scale(cs.kept, cs.alpha, cs.eps)
    return SoftModes(cs=cs, count=count, n_soft=count - cs.d, V=V, lo=nb.lo, hi=nb.hi, e=e,
                     rayleigh=nb.rayleigh, gap=nb.gap / scale, eq3=0.0, ortho=ortho,
                     overlap=np.stack([centres, f, f_nt], axis=1), trial_energy=E,
                     modulated_energy=Eg, e0=e0, omega_L2=omega_L2(e0, cs.kappa, cs.z_max, grad2),
                     grad2=grad2, omega_t2=omega_t2, n_below=n_below,
                     fractions=extended_fraction(e, cs.q))


# --------------------------------------------------------------------------- output

def gather_columns(comm, V, cols, root=0):
    """Rows of V[:, cols] from every rank, stacked on ``root`` (None elsewhere)."""
    parts = comm.tompi4py().gather(np.ascontiguousarray(V[:, cols]), root=root)
    return np.concatenate(parts, axis=0) if parts is not None else None


def write(comm, path, res, vectors=False, prov=None, block=64):
    """/softmodes/* (docs/file-format.md), written atomically on rank 0; the basis only with
    ``vectors`` (gathered to rank 0 in blocks of columns)."""
    rank = comm.getRank()
    if rank != 0:
        for start in range(0, res.n_soft, block) if vectors else []:
            gather_columns(comm, res.V, slice(start, start + block))
        return
    with io.atomic_h5(path) as f:
        io.write_h5md_header(f, prov)
        g = f.create_group("softmodes")
        _write_tables(g, res)
        if vectors:
            _write_basis(comm, g, res, block)


def _write_tables(g, res):
    cs = res.cs
    g.attrs["planes"] = np.array([p.label.encode() for p in cs.planes])
    g.attrs["planes_q"] = np.array(cs.per_plane, dtype=np.int64)
    g.create_dataset("cut_contacts", data=cs.cut_original())
    cnt = g.create_dataset("count", data=np.int64(res.count))
    for key, val in (("trivial", cs.trivial), ("localised", cs.localised), ("q", cs.q),
                     ("expected_if_isostatic", cs.expected), ("excess", cs.excess),
                     ("N_active", cs.n), ("Nc", len(cs.contacts)), ("n_basis", res.n_soft),
                     ("gap", res.gap), ("eq3_residual", res.eq3),
                     ("orthonormality", res.ortho)):
        cnt.attrs[key] = val
    cnt.attrs["localised_particles"] = cs.original[cs.localised_particles]
    ext = g.create_dataset("extension", data=res.e)
    ext.attrs["definition"] = "sum_i g_i^2 |dR_i|^2, g = product of sin(pi u/l) over cut axes"
    ov = g.create_dataset("overlap", data=res.overlap)
    ov.attrs["columns"] = ("x/L from the first plane, f (integral 1), f with the trivially "
                           "localised modes projected out (integral 1)")
    ov.attrs["axis"] = AXES[cs.planes[0].axis]
    ov.attrs["c"] = res.c_bound
    ov.attrs["c_nontrivial"] = res.c_nontrivial
    te = g.create_dataset("trial_energy", data=res.trial_energy)
    for key, val in (("e0", res.e0), ("omega_L2", res.omega_L2), ("grad_g_max2", res.grad2),
                     ("kappa", cs.kappa), ("z_max", cs.z_max), ("q_prime", res.q_prime),
                     ("omega_t2", res.omega_t2), ("n_below_2omega_t2", res.n_below),
                     ("mean_modulated_energy", float(np.mean(res.modulated_energy)))):
        te.attrs[key] = val
    fr = g.create_dataset("extended_fraction", data=res.fractions)
    fr.attrs["columns"] = "e0, q'/q"
    for key, val in res.solver.items():
        g.attrs[key] = val


def _write_basis(comm, g, res, block):
    cs = res.cs
    N = cs.n_total
    dset = g.create_dataset("basis", shape=(res.n_soft, N, cs.d), dtype="f8")
    dset.attrs["layout"] = "mode, particle (packing index; rattlers zero), component"
    for start in range(0, res.n_soft, block):
        cols = slice(start, min(start + block, res.n_soft))
        rows = gather_columns(comm, res.V, cols)
        full = np.zeros((rows.shape[1], N, cs.d))
        full[:, cs.original, :] = rows.T.reshape(rows.shape[1], cs.n, cs.d)
        dset[cols] = full
