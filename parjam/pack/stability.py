"""Is a force-balanced packing a stable minimum?  The lowest curvature of the full Hessian on the
non-rattlers, and the direction to leave a saddle along.

A state with max|F| below ftol can still be a saddle: near jamming the stress term of Eq. (1),
(V'(r)/r)(I - n n^T), is negative for repulsive contacts, so a network with too few contacts
(Nc < Nc_iso, blocked e.g. by a near-contact at a gap of ~1e-10) has modes of negative curvature
~ -p.  The check asks whether the full dynamical matrix D = M + M' (Eq. (1)) of the non-rattlers
has an eigenvalue below -s, where s is a small multiple of its round-off level
(SHIFT_ULPS * machine epsilon * ||D||_inf).  The d uniform translations are exact zero modes
and are deflated.  A state is *stable* when D has no eigenvalue below -s and it has Nc >= Nc_iso
contacts among its non-rattlers (a rigid network).

Two ways to answer, chosen by ``-stability_method`` (``METHODS``); the default ``auto`` takes the
exact inertia for matrices of at most ``-stability_auto_max_dof`` rows (AUTO_MAX_DOF), where its
factor is smaller than the engine's own arrays and one factorisation is far cheaper than the
thousands of Lanczos steps a state near jamming needs (3D N = 4096 at p = 1.4e-8: 0.8 s against
17,000 steps and 44 s of CPU, docs/results/stability.md), and the Lanczos test above:

- ``lanczos``: parjam.vib.lowest's Lanczos test on D, in O(N/P) memory per rank (the
  matrix and four vectors of this rank's rows).  "Unstable" is certified by a witness vector whose
  Rayleigh quotient lies below -2 s (Courant-Fischer); "stable" by the Lanczos-polynomial bound:
  the probability that an eigenvalue below -s was missed is at most ``-stability_lanczos_delta``
  (1e-10).  Where the test is inconclusive (its step budget ``-stability_lanczos_max_it`` runs
  out, or the lowest Ritz value converges inside the round-off band [-2 s, 0]), the exact inertia
  below decides if the matrix has at most ``-stability_exact_max_dof`` rows (EXACT_MAX_DOF);
  above that the state is *undecided* (n_negative = -1, not stable, never escaped from);
- ``inertia``: the number of eigenvalues below -s by Sylvester's law, the negative pivots of one
  MUMPS LDL^T of D + s I (parjam.vib.factor), its factor discarded as it is made.  Exact, but its
  memory grows as N^1.5 in 3D and its root front sits on one rank (docs/results/stability.md).

For an unstable state, ``softest_direction`` returns the eigenvector of the lowest
non-translational eigenvalue: the Lanczos test's witness (its Ritz vector, converged to
``-stability_lanczos_rtol``), or, after an exact count, SLEPc Krylov-Schur with shift-and-invert
at a target just below it, found from inertias, on the first rank with the rows gathered there
in id order (options prefix ``stability_``; up to ``-stability_auto_max_dof`` rows, above that
the Lanczos test run on until its lowest Ritz pair has converged).  The packing protocol
(parjam.pack.packing) follows it out of the saddle before minimising again.

Everything is distributed: the state is a parjam.pack.jamnet.JamNetwork (each rank its
slab of particles and the half-edges of their contacts), D is assembled from those half-edges
into block rows [lo, hi) of the active numbering (hessian.assemble(rows=...)), the softest
direction stays a distributed vector mapped back onto the owned particles, and the escape
searches move the owned particles and sum the energies of their contacts (one exact sum per
trial).  On one rank the matrix, its norm and every energy are the serial ones bitwise (the
half-edges come in the serial order, parjam.pack.jamnet), so the protocol takes the same path.
The Lanczos test is the same bits on any number of ranks (its start vector depends on the
particle ids only, its product sums each row in an order of ids, parjam.vib.rowproduct, and its
sums are exact), and so are the first rank's shift-and-invert on the rows gathered in id order
and the escapes' energies (exact sums): a member shared by P ranks leaves a saddle as it does
on one.  The exact inertia's count is an integer, the same unless an eigenvalue lies within
round-off of -s.
"""

from dataclasses import dataclass, field

import numpy as np

from parjam import env
from parjam.errors import ParjamError
from parjam.logevents import STABILITY_INERTIA, STABILITY_LANCZOS, event
from parjam.net import exactsum, potential
from parjam.pack import jamnet
from parjam.vib import factor, hessian, lowest, rowproduct
from parjam.net.active import max_op, min_op
from parjam.net.system import pair_separation, wrap

SHIFT_ULPS = 100.0  # s = SHIFT_ULPS * eps_machine * ||D||_inf
ESCAPE_MAX = 0.05  # escape searches stop at this displacement (in smallest diameters)
PREFIX = "stability_"
METHODS = ("auto", "lanczos", "inertia")
#: ``auto`` takes the exact inertia up to this many rows of D (3D N ~ 8300, 2D N = 12500): its
#: factor there is ~100 MB (745 MB x (N / 32768)^1.5 in 3D), less than the engine's arrays
AUTO_MAX_DOF = 25000
#: the exact inertia decides where the Lanczos test is inconclusive up to this many rows of D:
#: 98,304 rows (N = 32768 in 3D) took 745 MB in the factorisation (docs/results/stability.md)
EXACT_MAX_DOF = 100000


@dataclass
class Curvature:
    """Result of one stability check of a packing."""

    n_negative: int  # eigenvalues of D (non-rattlers) below -shift (Lanczos: those found);
    #                  -1: not computed, or undecided
    shift: float
    excess: int  # Nc - Nc_iso
    n_active: int
    method: str = "inertia"  # what decided: "lanczos", "inertia", or "undecided"
    lowest: float = np.nan  # lowest curvature seen (Lanczos: Ritz value or witness quotient)
    failure: float = 0.0  # Lanczos "stable": bound on the probability of a missed negative one
    steps: int = 0  # Lanczos steps
    why: str = ""  # why the Lanczos test was inconclusive, if it was
    mode: np.ndarray = field(default=None, repr=False, compare=False)  # witness, rows [lo, hi)
    mode_residual: float = np.inf  # ||D x - lowest x|| of the unit witness

    @property
    def stable(self):
        return self.n_negative == 0 and self.excess >= 0 and self.n_active > 0

    @property
    def decided(self):
        return self.n_negative >= 0


@dataclass
class Settings:
    """The check's options (prefix ``stability_``): -stability_method, -stability_exact_max_dof,
    -stability_auto_max_dof and the Lanczos test's -stability_lanczos_* (lowest.Settings)."""

    method: str = "auto"
    exact_max_dof: int = EXACT_MAX_DOF
    lanczos: lowest.Settings = None
    auto_max_dof: int = AUTO_MAX_DOF

    @classmethod
    def from_options(cls):
        opts = env.petsc().Options(PREFIX)
        method = opts.getString("method", "auto")
        if method not in METHODS:
            raise ParjamError(f"-{PREFIX}method {method}: choose from {', '.join(METHODS)}")
        auto = opts.getInt("auto_max_dof", AUTO_MAX_DOF)
        if auto < 0:
            raise ParjamError(f"-{PREFIX}auto_max_dof {auto}: must be >= 0")
        return cls(method, opts.getInt("exact_max_dof", EXACT_MAX_DOF),
                   lowest.Settings.from_options(PREFIX), auto)

    def method_for(self, dof):
        """The method that checks a matrix of ``dof`` rows: ``auto`` resolved by its size."""
        if self.method == "auto":
            return "inertia" if dof <= self.auto_max_dof else "lanczos"
        return self.method


@dataclass
class ActiveHessian:
    """This rank's block rows [lo, hi) of the full dynamical matrix of the non-rattlers (active
    numbers 0..N'-1), from the half-edges of a JamNetwork."""

    n: int
    d: int
    edges: jamnet.ActiveEdges
    blocks: np.ndarray
    norm: float  # ||D||_inf (global)

    def matrix(self, comm, shift=0.0):
        e = self.edges
        return hessian.assemble(comm, self.n, self.d, e.i, e.j, self.blocks, shift,
                                rows=(e.lo, e.hi))

    def product(self, comm):
        """Its rank-independent product v -> D v (parjam.vib.rowproduct; destroy it)."""
        e = self.edges
        return rowproduct.HalfEdgeProduct(comm, self.n, self.d, e.lo, e.hi, e.i, e.j,
                                          self.blocks)


def active_hessian(net):
    """The ActiveHessian of a JamNetwork (collective: one allreduce for the norm)."""
    e = net.active
    blocks = hessian.contact_blocks(e.rij, e.r, e.sigma, net.alpha, net.eps, "full")
    # ||D||_inf <= 2 max_i sum_j ||K_ij||_inf (diagonal block plus the off-diagonal ones); the
    # row sums taken as the serial bincounts over (i, j) then over (j, i) take them
    rowsum = block_row_norms(blocks)
    rows, m = e.i - e.lo, e.hi - e.lo
    per = (np.bincount(rows[:e.n_up], rowsum[:e.n_up], minlength=m)
           + np.bincount(rows[e.n_up:], rowsum[e.n_up:], minlength=m))
    top = float(per.max()) if len(per) else 0.0
    norm = net.state.comm.allreduce(top, op=max_op())
    return ActiveHessian(e.n, net.d, e, blocks, 2.0 * norm)


def block_row_norms(blocks):
    """||K||_inf = max_a sum_b |K_ab| of each d x d block, a row of blocks at a time: the
    values of ``np.abs(blocks).sum(axis=2).max(axis=1)`` without its temporary of the blocks'
    size (at 25,000 particles on one rank, 15 MB: the peak of the check)."""
    d, out = blocks.shape[1], None
    for a in range(d):
        s = np.abs(blocks[:, a, 0])
        for b in range(1, d):
            s += np.abs(blocks[:, a, b])
        out = s if out is None else np.maximum(out, s)
    return out


def shift_for(norm):
    return SHIFT_ULPS * np.finfo(np.float64).eps * max(norm, np.finfo(np.float64).tiny)


def count_below(comm, H, sigma):
    """Eigenvalues of the active Hessian below sigma (< 0): negative pivots of the MUMPS LDL^T
    of D - sigma I; without MUMPS, dense LAPACK on every rank (small systems only)."""
    PETSc = env.petsc()
    if not env.has_mumps():
        return count_below_dense(comm, H, sigma)
    with event(STABILITY_INERTIA):
        A = H.matrix(comm, -sigma)
        ksp = PETSc.KSP().create(comm=comm)
        try:
            ksp.setOptionsPrefix(PREFIX)
            factor.direct_cholesky(ksp)
            ksp.setOperators(A)
            ksp.setFromOptions()
            factor.exact_inertia(ksp.getPC(), inertia_only=True)
            ksp.setUp()
            count = factor.negative_pivots(ksp.getPC())
        finally:
            ksp.destroy()
            A.destroy()
    return -1 if count is None else int(count)


def count_below_dense(comm, H, sigma):
    """The dense fall-back of ``count_below`` (no MUMPS): every contact once (the half-edges
    whose owned end has the lower id) gathered, LAPACK on every rank; small systems only."""
    e, k = H.edges, H.edges.n_up
    got = comm.tompi4py().allgather((e.i[:k], e.j[:k], H.blocks[:k]))
    i, j, b = (np.concatenate(p) for p in zip(*got))
    D = hessian.dense_hessian(H.n, H.d, i, j, b.reshape(-1, H.d, H.d))
    return int(np.sum(np.linalg.eigvalsh(D) < sigma))


def check(comm, net, settings=None):
    """Curvature of the state of JamNetwork ``net`` (collective on comm), by the method of
    ``settings`` (default: from the options database; see the module doc)."""
    if net.n_active == 0:
        return Curvature(0, 0.0, net.excess, 0)
    cfg = settings or Settings.from_options()
    H = active_hessian(net)
    s = shift_for(H.norm)
    if cfg.method_for(H.n * H.d) == "inertia":
        return Curvature(count_below(comm, H, -s), s, net.excess, net.n_active)
    res = lanczos_test(comm, H, s, cfg.lanczos)
    args = (s, net.excess, net.n_active)
    info = {"lowest": res.lowest, "steps": res.steps}
    if res.verdict == lowest.BELOW:
        return Curvature(res.n_below, *args, "lanczos", mode=res.vector,
                         mode_residual=res.residual, **info)
    if res.verdict == lowest.NOT_BELOW:
        return Curvature(0, *args, "lanczos", failure=res.failure, **info)
    if H.n * H.d <= cfg.exact_max_dof:
        return Curvature(count_below(comm, H, -s), *args, "inertia", why=res.why, **info)
    return Curvature(-1, *args, "undecided", why=res.why, **info)


def lanczos_test(comm, H, s, settings=None, want_vector=False):
    """parjam.vib.lowest's test of the ActiveHessian ``H`` against -s, from the start vector of
    its particles' ids, with its rank-independent product (collective)."""
    with event(STABILITY_LANCZOS):
        op = H.product(comm)
        try:
            st = settings or lowest.Settings.from_options(PREFIX)
            start = lowest.start_rows(H.edges.ids, H.d, st.seed)
            return lowest.lowest_test(op, H.d, s, start, st, want_vector=want_vector)
        finally:
            op.destroy()


def softest_direction(comm, net, curvature):
    """Displacement of the owned particles (rows of ``net.state``) along the lowest
    non-translational eigenvector of the active Hessian, zero on rattlers, scaled to a largest
    particle displacement of 1 over all ranks, and its eigenvalue; (None, nan) if none is
    found.  The Lanczos check's witness where that has converged to an eigenvector; else, up to
    ``-stability_auto_max_dof`` rows, shift-and-invert on the first rank (``root_softest``), and
    above, the Lanczos test run on until its lowest Ritz pair has converged.  Each is the same
    bits on any number of ranks, so the escape from a saddle is too."""
    cfg = Settings.from_options()
    if curvature.mode is not None and curvature.mode_residual <= max(
            cfg.lanczos.rtol * abs(curvature.lowest), lowest.FLOOR * curvature.shift):
        vec, lam = curvature.mode, curvature.lowest
    elif net.n_active * net.d <= cfg.auto_max_dof and env.has_mumps():
        vec, lam = root_softest(net, curvature)
    else:  # the witness is not yet an eigenvector, or there is none: converge the lowest pair
        res = lanczos_test(comm, active_hessian(net), curvature.shift, cfg.lanczos,
                           want_vector=True)
        vec, lam = res.vector, res.lowest
    if vec is None:
        return None, np.nan
    out = np.zeros((len(net.state.ids), net.d))
    out[~net.rattler] = vec.reshape(-1, net.d)
    norms = np.sqrt(np.einsum("ij,ij->i", out, out))
    top = net.state.comm.allreduce(float(norms.max()) if len(norms) else 0.0, op=max_op())
    return out / top, lam


def root_softest(net, curvature):
    """The lowest non-translational eigenpair of the active Hessian by shift-and-invert on the
    first rank: this rank's rows of the vector and the eigenvalue, or (None, nan) (collective).

    The rows are gathered there and renumbered by particle id (``root_hessian``), so the first
    rank holds the same matrix, bit for bit, whatever the number of ranks; inertias of one
    sequential MUMPS LDL^T at -10 s, -100 s ... put a target below the lowest eigenvalue, and
    SLEPc Krylov-Schur (sequential, its own start vector) finds the eigenpair nearest it.  All
    of it is sequential code on the same numbers, so the vector is the same bits on 1 or P
    ranks (a distributed factorisation's round-off depends on the split).  Its memory is one
    factor on one rank: ``softest_direction`` takes it up to -stability_auto_max_dof rows."""
    PETSc = env.petsc()
    mpi = net.state.comm
    H = active_hessian(net)
    got = mpi.gather((H.edges.ids, H.edges.i, H.edges.j, H.blocks), root=0)
    out = None
    if mpi.Get_rank() == 0:
        root, number = root_hessian(H, got)
        s = curvature.shift
        target = -s
        if curvature.n_negative > 0:
            target = -10.0 * s
            while count_below(PETSc.COMM_SELF, root, target) > 0 and \
                    target > -1e6 * max(root.norm, 1.0):
                target *= 10.0
        vec, lam = nearest_mode(PETSc.COMM_SELF, root, target)
        rows = vec.reshape(-1, H.d) if vec is not None else None
        out = [(None if rows is None else rows[number[ids]], lam) for ids, *_ in got]
    return mpi.scatter(out, root=0)


def root_hessian(H, parts):
    """The whole active Hessian on one rank, rows numbered by particle id, from every rank's
    (ids, i, j, blocks) in rank order (active numbers are the ranks' consecutive blocks): an
    ActiveHessian of rows [0, N'), and the row of each particle id ({id: row} as an array).  A
    row's half-edges keep their owner's order (partners by id), so its diagonal block is the
    same sum on any number of ranks."""
    ids = np.concatenate([p[0] for p in parts])
    order = np.argsort(ids, kind="stable")
    renumber = np.empty(len(ids), dtype=np.int64)
    renumber[order] = np.arange(len(ids))
    number = np.full(int(ids.max()) + 1 if len(ids) else 0, -1, dtype=np.int64)
    number[ids] = renumber
    i = renumber[np.concatenate([p[1] for p in parts])]
    j = renumber[np.concatenate([p[2] for p in parts])]
    blocks = np.concatenate([p[3] for p in parts])
    n, none = len(ids), np.zeros((0, H.d))
    edges = jamnet.ActiveEdges(n, 0, n, 0, i, j, none, none[:, 0], none[:, 0], ids[order])
    return ActiveHessian(n, H.d, edges, blocks, H.norm), number


def nearest_mode(comm, H, target):
    """Eigenpair of the active Hessian nearest ``target``, translations deflated: this rank's
    rows [lo, hi) of the eigenvector (a copy) and the eigenvalue, or (None, nan)."""
    SLEPc = env.slepc()
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
        vec = np.array(xr.array_r)
        xr.destroy()
        return vec, float(lam)
    finally:
        eps.destroy()
        for v in deflation:
            v.destroy()
        A.destroy()


def moved(state, direction, t):
    """The owned rows of ``state`` displaced by t * direction, wrapped into the box."""
    return wrap(state.x + t * direction, state.L)


def escape_candidates(net, direction):
    """Displacements t along ``direction`` (owned rows of ``net.state``, unit max-norm) to
    leave a saddle from, best first:

    - on each side, the displacement where the first new contact closes (geometric search, then
      bisection to round-off): a saddle blocked by a near-contact (Nc = Nc_iso - 1, a gap of
      ~1e-10 .. 1e-8) becomes a stable minimum with that contact.  Its equilibrium overlap is
      ~ |lambda| * gap / k ~ p * gap, below the round-off of 1 - r/sigma (1e-16) at dphi <= 1e-8:
      double precision holds it as a contact of a few ulps, balanced to far below --ftol;
    - the lowest energy along the line (doubling steps, then golden section): a saddle whose
      descent is not blocked nearby.
    Sides are ordered by the energy at their new contact.  Every trial moves the owned
    particles, hands them to their slabs and evaluates their contacts there (collective).
    ``moved(net.state, direction, t)`` gives the positions of a candidate."""
    st = net.state
    dmin = st.comm.allreduce(float(st.diam.min()) if len(st.diam) else np.inf, op=min_op())
    lim = ESCAPE_MAX * dmin
    trials = LineTrials(st, direction, net.alpha, net.eps)
    touch = []
    for sign in (1.0, -1.0):
        t_lo, t = 0.0, 1e-15
        while t <= lim and not trials.new_contact(sign * t):
            t_lo, t = t, 2.0 * t
        if t > lim:
            continue
        t_hi = t
        for _ in range(80):
            mid = 0.5 * (t_lo + t_hi)
            if mid in (t_lo, t_hi):
                break
            if trials.new_contact(sign * mid):
                t_hi = mid
            else:
                t_lo = mid
        touch.append((trials.energy(sign * t_hi), sign * t_hi))
    touch.sort(key=lambda c: c[0])
    return [t for _, t in touch] + [_line_minimum(trials.energy, lim)]


class LineTrials:
    """Energies and new contacts of a state displaced along a direction: the owned rows moved,
    migrated to their slabs (with their unmoved positions along), and their contacts there."""

    def __init__(self, state, direction, alpha, eps):
        self.state, self.direction = state, direction
        self.alpha, self.eps = alpha, eps

    def _contacts(self, t):
        st = self.state
        x, ids, f = st.dom.migrate(moved(st, self.direction, t), st.ids,
                                   {"diam": st.diam, "base": st.x})
        here = jamnet.SlabState(st.comm, st.dom, st.L, x, ids, f["diam"], st.cutoff)
        edges, halo, _, once = jamnet.contact_edges(here)
        return edges.subset(once), halo, f["base"]

    def energy(self, t):
        """Total energy at displacement t (each contact once, an exact sum over the ranks:
        the same bits on any number of ranks)."""
        c, _, _ = self._contacts(t)
        return exactsum.fsum(self.state.comm, potential.energy(c.r, c.sigma, self.alpha,
                                                               self.eps))

    def new_contact(self, t):
        """Whether some contact at displacement t was not one at t = 0 (the same separation
        test as the contacts themselves, on the unmoved positions)."""
        c, halo, base = self._contacts(t)
        pts = np.concatenate([base, halo.pull(base)])
        rij = pair_separation(pts[c.i], pts[c.j], self.state.dom.L)
        r0 = np.sqrt(np.einsum("ij,ij->i", rij, rij))
        return bool(self.state.comm.allreduce(int(np.any(r0 >= c.sigma)), op=max_op()))


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
