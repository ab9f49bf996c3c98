"""Is a force-balanced packing a stable minimum?  The lowest curvature of the full Hessian on the
non-rattlers, and the direction to leave a saddle along.

A state with max|F| below ftol can still be a saddle: near jamming the stress term of Eq. (1),
(V'(r)/r)(I - n n^T), is negative for repulsive contacts, so a network with too few contacts
(Nc < Nc_iso, blocked e.g. by a near-contact at a gap of ~1e-10) has modes of negative curvature
~ -p.  The check counts the eigenvalues of the full dynamical matrix D = M + M' (Eq. (1)) of
the non-rattlers below -s, where s is a small multiple of its round-off level
(SHIFT_ULPS * machine epsilon * ||D||_inf): the inertia (Sylvester's law) of an LDL^T
factorisation of D + s I by MUMPS (parjam.factor), one factorisation, on any number of ranks.
The d uniform translations are exact zero modes and sit at +s, above the threshold.

A state is *stable* when no eigenvalue lies below -s and it has Nc >= Nc_iso contacts among
its non-rattlers (a rigid network).  For an unstable one, ``softest_direction`` returns the
eigenvector of the lowest non-translational eigenvalue (SLEPc Krylov-Schur with
shift-and-invert at a target just below it, found from inertias, options prefix
``stability_``), which the packing protocol (parjam.packing) follows out of the saddle before
minimising again.
"""

from dataclasses import dataclass

import numpy as np

from parjam import env, factor, hessian, potential
from parjam.network import analyze, find_contacts
from parjam.system import wrap

SHIFT_ULPS = 100.0  # s = SHIFT_ULPS * eps_machine * ||D||_inf
ESCAPE_MAX = 0.05  # escape searches stop at this displacement (in smallest diameters)
PREFIX = "stability_"


@dataclass
class Curvature:
    """Result of one stability check of a packing."""

    n_negative: int  # eigenvalues of D (non-rattlers) below -shift; -1: not computed
    shift: float
    excess: int  # Nc - Nc_iso
    n_active: int

    @property
    def stable(self):
        return self.n_negative == 0 and self.excess >= 0 and self.n_active > 0


@dataclass
class ActiveHessian:
    """The full dynamical matrix of the non-rattlers, re-indexed 0..N'-1 (contacts among them)."""

    n: int
    d: int
    active: np.ndarray  # original indices of the non-rattlers
    i: np.ndarray
    j: np.ndarray
    blocks: np.ndarray
    norm: float  # ||D||_inf

    def matrix(self, comm, shift=0.0):
        lo, hi = hessian.row_range(self.n, comm)
        mine = ((self.i >= lo) & (self.i < hi)) | ((self.j >= lo) & (self.j < hi))
        return hessian.assemble(comm, self.n, self.d, self.i[mine], self.j[mine],
                                self.blocks[mine], shift)


def active_hessian(pack, net=None):
    net = net if net is not None else analyze(pack)
    keep = ~net.rattler
    index = np.cumsum(keep) - 1
    c = net.contacts
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    n = int(keep.sum())
    # ||D||_inf <= 2 max_i sum_j ||K_ij||_inf (diagonal block plus the off-diagonal ones)
    rowsum = np.abs(blocks).sum(axis=2).max(axis=1) if len(blocks) else np.zeros(0)
    per = (np.bincount(index[c.i], rowsum, minlength=n)
           + np.bincount(index[c.j], rowsum, minlength=n)) if n else np.zeros(1)
    return ActiveHessian(n, pack.d, np.nonzero(keep)[0], index[c.i], index[c.j], blocks,
                         2.0 * float(per.max()) if len(per) else 0.0)


def shift_for(norm):
    return SHIFT_ULPS * np.finfo(np.float64).eps * max(norm, np.finfo(np.float64).tiny)


def count_below(comm, H, sigma):
    """Eigenvalues of the active Hessian below sigma (< 0): negative pivots of the MUMPS LDL^T
    of D - sigma I; without MUMPS, dense LAPACK on every rank (small systems only)."""
    PETSc = env.petsc()
    if not env.has_mumps():
        return _count_below_dense(H, sigma)
    A = H.matrix(comm, -sigma)
    ksp = PETSc.KSP().create(comm=comm)
    try:
        ksp.setOptionsPrefix(PREFIX)
        factor.direct_cholesky(ksp)
        ksp.setOperators(A)
        ksp.setFromOptions()
        factor.exact_inertia(ksp.getPC())
        ksp.setUp()
        count = factor.negative_pivots(ksp.getPC())
    finally:
        ksp.destroy()
        A.destroy()
    return -1 if count is None else int(count)


def _count_below_dense(H, sigma):
    D = hessian.dense_hessian(H.n, H.d, H.i, H.j, H.blocks)
    return int(np.sum(np.linalg.eigvalsh(D) < sigma))


def check(comm, pack, net=None):
    """Curvature of the current state (collective on comm; every rank passes the same pack)."""
    net = net if net is not None else analyze(pack)
    if net.n_active == 0:
        return Curvature(0, 0.0, net.excess, 0)
    H = active_hessian(pack, net)
    s = shift_for(H.norm)
    return Curvature(count_below(comm, H, -s), s, net.excess, net.n_active)


def softest_direction(comm, pack, curvature, net=None):
    """(N, d) unit-max-norm displacement along the lowest non-translational eigenvector of the
    active Hessian (zero on rattlers), and its eigenvalue; (None, nan) if SLEPc does not find
    it.  The target lies below the lowest eigenvalue (from inertias at -s, -10 s, -100 s ...),
    so the eigenvalue nearest it is the lowest."""
    net = net if net is not None else analyze(pack)
    H = active_hessian(pack, net)
    s = curvature.shift
    target = -s
    if curvature.n_negative > 0:
        target = -10.0 * s
        while count_below(comm, H, target) > 0 and target > -1e6 * max(H.norm, 1.0):
            target *= 10.0
    vec, lam = _nearest_mode(comm, H, target)
    if vec is None:
        return None, np.nan
    out = np.zeros((pack.n, pack.d))
    out[H.active] = vec.reshape(H.n, H.d)
    norms = np.sqrt(np.einsum("ij,ij->i", out, out))
    return out / norms.max(), lam


def _nearest_mode(comm, H, target):
    """Eigenpair of the active Hessian nearest ``target``, translations deflated (on every rank:
    the full vector)."""
    PETSc, SLEPc = env.petsc(), env.slepc()
    A = H.matrix(comm)
    deflation = []
    for a in range(H.d):
        v = A.createVecRight()
        arr = v.getArray()
        arr[:] = 0.0
        arr.reshape(-1, H.d)[:, a] = 1.0 / np.sqrt(H.n)
        deflation.append(v)
    eps = SLEPc.EPS().create(comm)
    try:
        eps.setOperators(A)
        eps.setProblemType(SLEPc.EPS.ProblemType.HEP)
        eps.setType(SLEPc.EPS.Type.KRYLOVSCHUR)
        eps.setDimensions(nev=1)
        eps.setTarget(target)
        eps.setWhichEigenpairs(SLEPc.EPS.Which.TARGET_MAGNITUDE)
        eps.setTolerances(tol=1e-8, max_it=500)
        eps.setDeflationSpace(deflation)
        st = eps.getST()
        st.setType("sinvert")
        factor.direct_cholesky(st.getKSP(), fallback="lu")
        eps.setOptionsPrefix(PREFIX)
        eps.setFromOptions()
        eps.solve()
        if eps.getConverged() < 1:
            return None, np.nan
        xr = A.createVecRight()
        lam = eps.getEigenpair(0, xr).real
        scatter, full = PETSc.Scatter.toAll(xr)
        scatter.scatter(xr, full, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        vec = np.array(full.array_r)
        for obj in (scatter, full, xr):
            obj.destroy()
        return vec, float(lam)
    finally:
        eps.destroy()
        for v in deflation:
            v.destroy()
        A.destroy()


def escape_candidates(pack, direction):
    """Positions to leave a saddle from, along ``direction`` (unit max-norm), best first:

    - on each side, the displacement where the first new contact closes (geometric search, then
      bisection to round-off): a saddle blocked by a near-contact (Nc = Nc_iso - 1, a gap of
      ~1e-10 .. 1e-8) becomes a stable minimum with that contact.  Its equilibrium overlap is
      ~ |lambda| * gap / k ~ p * gap, below the round-off of 1 - r/sigma (1e-16) at dphi <= 1e-8:
      double precision holds it as a contact of a few ulps, balanced to far below --ftol;
    - the lowest energy along the line (doubling steps, then golden section): a saddle whose
      descent is not blocked nearby.
    Sides are ordered by the energy at their new contact."""
    lim = ESCAPE_MAX * float(pack.diam.min())
    base = _pair_set(pack, pack.pos)

    def moved(t):
        return wrap(pack.pos + t * direction, pack.L)

    def energy(t):
        c = find_contacts(_with(pack, moved(t)))
        return float(potential.energy(c.r, c.sigma, pack.alpha, pack.eps).sum())

    touch = []
    for sign in (1.0, -1.0):
        t_lo, t = 0.0, 1e-15
        while t <= lim and not (_pair_set(pack, moved(sign * t)) - base):
            t_lo, t = t, 2.0 * t
        if t > lim:
            continue
        t_hi = t
        for _ in range(80):
            mid = 0.5 * (t_lo + t_hi)
            if mid in (t_lo, t_hi):
                break
            if _pair_set(pack, moved(sign * mid)) - base:
                t_hi = mid
            else:
                t_lo = mid
        touch.append((energy(sign * t_hi), moved(sign * t_hi)))
    touch.sort(key=lambda c: c[0])
    return [pos for _, pos in touch] + [moved(_line_minimum(energy, lim))]


def _with(pack, pos):
    p = pack.copy()
    p.pos = pos
    return p


def _pair_set(pack, pos):
    c = find_contacts(_with(pack, pos))
    return set(zip(c.i.tolist(), c.j.tolist()))


def _line_minimum(energy, lim):
    """t of the lowest energy(t) found on either side: doubling steps from 1e-12 until the
    energy rises, then a golden-section search in the last bracket."""
    e0 = energy(0.0)
    best = (e0, 0.0)
    for sign in (1.0, -1.0):
        ts, es, t = [0.0], [e0], sign * 1e-12
        while abs(t) <= lim:
            ts.append(t)
            es.append(energy(t))
            if es[-1] < best[0]:
                best = (es[-1], t)
            if es[-1] > es[-2] and len(ts) > 2 and es[-2] < e0:
                break
            t *= 2.0
        if best[1] in ts[1:-1]:
            k = ts.index(best[1])
            a, b = ts[k - 1], ts[k + 1]
            for _ in range(40):
                m1, m2 = b - 0.618 * (b - a), a + 0.618 * (b - a)
                e1, e2 = energy(m1), energy(m2)
                for e, tt in ((e1, m1), (e2, m2)):
                    if e < best[0]:
                        best = (e, tt)
                if e1 < e2:
                    b = m2
                else:
                    a = m1
    return best[1]
