"""Stochastic density of states D(omega) for large N: the kernel polynomial method (KPM).

Weisse, Wellein, Alvermann & Fehske, Rev. Mod. Phys. 78, 275 (2006), applied to the dynamical
matrix A (full D = M + M', relaxed M or stress M' of the paper's Eq. (1)) of the non-rattlers.
Only distributed PETSc MatMult and vector operations are used, so it runs on any number of ranks
at the cost of (moments / 2) products per probe vector and no factorisation.

1. Bounds [a, b] of the spectrum: b from a short Lanczos run (the top Ritz value plus its
   residual and a margin), capped by ||A||_inf (Gershgorin); a = -margin * b for the full and
   relaxed matrices (positive semi-definite for a stable packing; lower if Lanczos finds a
   negative Ritz value), from Lanczos for the stress term.  A~ = (A - c) / h with c = (a + b) / 2, h = (b - a) / 2 has its spectrum in [-1, 1].
2. Chebyshev moments (RMP Eq. 71, 74)  mu_n = tr(P T_n(A~)) / (d N' - d), P the projector off
   the d uniform translations (exact zero modes of the periodic box): each probe r = P z,
   z with i.i.d. +-1 (default) or Gaussian entries, gives r^T T_n(A~) r, whose mean over z is
   tr(P T_n(A~)).  Three-term recurrence t_{n+1} = 2 A~ t_n - t_{n-1} with moment doubling
   mu_{2n} = 2 <t_n, t_n> - mu_0, mu_{2n+1} = 2 <t_{n+1}, t_n> - mu_1 (RMP Eq. 73): M moments
   cost M / 2 products.  Rattlers are removed before (as in parjam.vib.spectrum), so their exact
   zero modes never enter; the translations are projected out of every probe, so
   n_modes = d N' - d is the exact trace of P and mu_0 = 1.
3. Jackson kernel g_n (RMP Eq. 71) against Gibbs oscillations; the density of x = lambda~ is
   rho(x) = [g_0 mu_0 + 2 sum_n g_n mu_n T_n(x)] / (pi sqrt(1 - x^2))  (RMP Eq. 70), and its
   cumulative, with x = cos(theta),
       F(x) = 1 - [g_0 mu_0 theta + 2 sum_n g_n mu_n sin(n theta) / n] / pi,
   exactly integrated, so bin counts need no quadrature.
4. D(omega) per mode, omega = sqrt(lambda): on a bin [w1, w2] the fraction of modes is
   F(w2^2) - F(w1^2), divided by the bin width; pointwise D(omega) = 2 omega rho_lambda(omega^2)
   (the Jacobian d lambda / d omega = 2 omega).  The Jackson kernel smears the edge at lambda = 0
   into lambda < 0 by about its resolution; that weight belongs to the lowest modes and is
   counted in the lowest bin (reported as ``weight_below_zero``).

Probe vectors depend only on (seed, probe index) and the particle, never on the rank count or
the numbering of the rows: entry (particle p, component a) is number p d + a of a vector
generated in fixed chunks of CHUNK entries, each from its own
``numpy.random.SeedSequence([seed, 0, probe, chunk])``; each rank generates only the chunks
holding its particles (the keys are the particle ids of its rows, ``ActiveSystem.ids``).  1 and 2 ranks therefore
give the same moments up to the round-off of the parallel sums, with the serial re-index and
with the slab numbering of parjam.net.active alike.

PETSc log stages: ``kpm: bounds`` and ``kpm: moments`` (``-log_view``).
"""

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from parjam import env
from parjam.vib import observables, spectrum, translations
from parjam.errors import ParjamError
from parjam.logstage import log_stage

CHUNK = 1 << 16  # entries per independently seeded chunk of a probe vector
PROBES = ("rademacher", "gaussian")
SEMIDEFINITE = ("full", "relaxed")
ROUNDOFF = 1e-6  # |r^T T_n r| may exceed |r|^2 by this relative amount before we call it growth


# --- probe vectors, independent of the rank count ---------------------------------------------
def probe_values(seed, probe, lo, hi, kind="rademacher", stream=0):
    """Entries [lo, hi) of probe number ``probe``: the same numbers on any rank layout
    (``stream`` 0 for the moment probes, 1 for the Lanczos start of the bounds)."""
    if kind not in PROBES:
        raise ParjamError(f"unknown probe kind {kind!r}; choose from {', '.join(PROBES)}")
    out = np.empty(hi - lo)
    for chunk in range(lo // CHUNK, (hi - 1) // CHUNK + 1 if hi > lo else lo // CHUNK):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), stream, int(probe), chunk]))
        c0 = chunk * CHUNK
        vals = (rng.integers(0, 2, CHUNK) * 2.0 - 1.0 if kind == "rademacher"
                else rng.standard_normal(CHUNK))
        s, e = max(lo, c0), min(hi, c0 + CHUNK)
        out[s - lo:e - lo] = vals[s - c0:e - c0]
    return out


def probe_entries(seed, probe, index, kind="rademacher", stream=0):
    """Entries number ``index`` (any global indices) of probe number ``probe``: the numbers of
    ``probe_values`` at those places, generating only the chunks that hold them."""
    index = np.asarray(index, dtype=np.int64)
    out = np.empty(len(index))
    chunk = index // CHUNK
    for c in np.unique(chunk):
        sel = chunk == c
        rel = index[sel] - c * CHUNK
        out[sel] = probe_values(seed, probe, int(c) * CHUNK, int(c) * CHUNK + CHUNK, kind,
                                stream)[rel]
    return out


def fill_probe(v, seed, probe, kind, stream=0, keys=None):
    """Fill v with probe ``probe``.  ``keys``: the particle id of each local block row, so that
    the probe entry of (particle p, component a) is entry p d + a whatever the rank layout and
    the numbering of the rows (parjam.net.active numbers rows by slab); None: the row index."""
    lo, hi = v.getOwnershipRange()
    if keys is None:
        v.getArray()[:] = probe_values(seed, probe, lo, hi, kind, stream)
        return
    d = (hi - lo) // max(len(keys), 1) if len(keys) else 1
    index = (np.asarray(keys, dtype=np.int64)[:, None] * d + np.arange(d)).ravel()
    v.getArray()[:] = probe_entries(seed, probe, index, kind, stream)


# --- spectral bounds ---------------------------------------------------------------------------
def lanczos_ritz(A, v0, steps):
    """Extreme Ritz values of A from ``steps`` Lanczos steps from v0 (plain three-term recurrence;
    the extreme Ritz values converge first) and the residual norms |beta_m s_m| of those Ritz
    pairs, each bounding the distance from its Ritz value to an eigenvalue."""
    q = v0.copy()
    q.scale(1.0 / q.norm())
    q_prev = q.duplicate()
    q_prev.set(0.0)
    w = q.duplicate()
    alpha, beta = [], []
    b_prev = 0.0
    for _ in range(steps):
        A.mult(q, w)
        a = w.dot(q)
        w.axpy(-a, q)
        w.axpy(-b_prev, q_prev)
        b = w.norm()
        alpha.append(a)
        beta.append(b)
        if b <= 1e-14 * max(abs(a), 1.0):
            break
        q_prev, q, w = q, w, q_prev
        q.scale(1.0 / b)
        b_prev = b
    for obj in (q, q_prev, w):
        obj.destroy()
    theta, s = scipy.linalg.eigh_tridiagonal(np.array(alpha), np.array(beta[:-1]))
    resid = np.abs(beta[-1] * s[-1, :])
    return theta[0], resid[0], theta[-1], resid[-1]


def spectral_bounds(A, d, kind, seed, steps=40, margin=1e-3, keys=None):
    """[a, b] enclosing the spectrum of A (see the module doc), and a record of how."""
    PETSc = env.petsc()
    norm = A.norm(PETSc.NormType.INFINITY)  # Gershgorin: |lambda| <= ||A||_inf
    unstable = False
    v = A.createVecRight()
    fill_probe(v, seed, 0, "gaussian", stream=1, keys=keys)
    translations.project(v, d)
    tmin, rmin, tmax, rmax = lanczos_ritz(A, v, min(steps, A.getSize()[0]))
    v.destroy()
    b = min(norm, tmax + max(rmax, 0.01 * abs(tmax)))
    if kind in SEMIDEFINITE:
        a = -margin * b
        if tmin < a:  # an unstable packing: Lanczos found a negative eigenvalue, enclose it
            a = max(-norm, tmin - max(rmin, 0.01 * abs(tmin))) - margin * b
            unstable = True
    else:
        a = max(-norm, tmin - max(rmin, 0.01 * abs(tmin)))
        span = b - a
        a, b = a - margin * span, b + margin * span
    return a, b, {"norm_inf": norm, "lanczos_steps": steps, "ritz_max": tmax,
                  "ritz_max_residual": rmax, "ritz_min": tmin, "ritz_min_residual": rmin,
                  "negative_ritz": unstable}


# --- Chebyshev moments ---------------------------------------------------------------------------
def jackson(m):
    """Jackson kernel g_0..g_{m-1} (RMP Eq. 71)."""
    n = np.arange(m)
    q = np.pi / (m + 1)
    return ((m - n + 1) * np.cos(q * n) + np.sin(q * n) / np.tan(q)) / (m + 1)


class Recurrence:
    """The Chebyshev recurrence of one probe r, resumable: ``advance(M)`` returns
    r^T T_n(A~) r for n < M (raw sums, moment doubling: M / 2 products in all), continuing
    from where the previous call stopped, so doubling the moments costs only the new ones."""

    def __init__(self, A, r, c, h):
        self.A, self.c, self.h = A, c, h
        self.t_prev = r.copy()
        self.t = r.duplicate()
        self.w = r.duplicate()
        A.mult(self.t_prev, self.t)  # t_1 = A~ r
        self.t.axpy(-c, self.t_prev)
        self.t.scale(1.0 / h)
        self.mu0 = self.t_prev.dot(self.t_prev)
        self.mu1 = self.t.dot(self.t_prev)
        self.mu = [self.mu0, self.mu1, 2.0 * self.t.dot(self.t) - self.mu0]  # 2 <t1,t1> - mu0
        self.n = 1

    def advance(self, moments):
        half = (moments + 1) // 2
        while self.n < half:
            self.A.mult(self.t, self.w)  # t_{n+1} = 2 A~ t_n - t_{n-1}
            self.w.axpy(-self.c, self.t)
            self.w.scale(2.0 / self.h)
            self.w.axpy(-1.0, self.t_prev)
            self.mu.append(2.0 * self.w.dot(self.t) - self.mu1)
            self.mu.append(2.0 * self.w.dot(self.w) - self.mu0)
            self.t_prev, self.t, self.w = self.t, self.w, self.t_prev
            self.n += 1
        return np.array(self.mu[:moments])

    def destroy(self):
        for obj in (self.t_prev, self.t, self.w):
            obj.destroy()


def probe_moments(A, r, c, h, moments):
    """r^T T_n(A~) r for n < moments (moment doubling: moments / 2 products), A~ = (A - c) / h.
    Returns the raw sums (not normalised by |r|^2)."""
    rec = Recurrence(A, r, c, h)
    try:
        return rec.advance(moments)
    finally:
        rec.destroy()


@dataclass
class KPMResult:
    """Chebyshev moments of the spectral density of one matrix and everything to evaluate it."""

    moments: np.ndarray  # mu_n averaged over probes, mu_0 = 1
    probe_moments: np.ndarray  # (probes, M): per-probe estimates, normalised by n_modes
    a: float
    b: float
    n_modes: int  # d N' - d
    matrix: str
    probe_kind: str
    seed: int
    info: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def n_moments(self):
        return len(self.moments)

    @property
    def n_probes(self):
        return len(self.probe_moments)

    @property
    def omega_max(self):
        return float(np.sqrt(max(self.b, 0.0)))

    def scaled(self, lam):
        return (np.asarray(lam, dtype=float) - 0.5 * (self.a + self.b)) / (0.5 * (self.b - self.a))

    def cumulative(self, lam, mu=None):
        """F(lambda): the fraction of the d N' - d modes with eigenvalue <= lambda."""
        return cumulative(self.moments if mu is None else mu, self.scaled(lam))

    def density_lambda(self, lam, mu=None):
        """rho(lambda) per mode (integrates to 1 over [a, b])."""
        h = 0.5 * (self.b - self.a)
        return density_x(self.moments if mu is None else mu, self.scaled(lam)) / h

    def density_omega(self, omega, mu=None):
        """Pointwise D(omega) = 2 omega rho(omega^2), per mode."""
        w = np.asarray(omega, dtype=float)
        return 2.0 * w * self.density_lambda(w * w, mu)

    @property
    def fold_below_zero(self):
        """The weight below lambda = 0 is the kernel's smearing of the lowest modes (counted in
        the lowest bin) unless the matrix may be indefinite (stress term, or a negative Ritz
        value: an unstable packing, whose negative modes are then left out of D(omega))."""
        return self.matrix in SEMIDEFINITE and not self.info.get("negative_ritz", False)

    def binned(self, edges, mu=None):
        """D(omega) per mode on omega bins: (F(w2^2) - F(w1^2)) / (w2 - w1); the smeared weight
        below lambda = 0 goes to a bin starting at omega = 0 (see fold_below_zero)."""
        e = np.asarray(edges, dtype=float)
        F = self.cumulative(e * e, mu)
        if e[0] == 0.0 and self.fold_below_zero:
            F[0] = 0.0
        return np.diff(F) / np.diff(e)

    def binned_with_error(self, edges):
        """D(omega) on bins and its standard error over the probes."""
        dens = self.binned(edges)
        if self.n_probes < 2:
            return dens, np.zeros_like(dens)
        each = np.array([self.binned(edges, self._normalised(p)) for p in self.probe_moments])
        return dens, each.std(axis=0, ddof=1) / np.sqrt(self.n_probes)

    def _normalised(self, p):
        mu = np.array(p, dtype=float)
        mu[0] = 1.0
        return mu

    @property
    def weight_below_zero(self):
        return float(self.cumulative(0.0))


CHUNK_ENTRIES = 1 << 22  # points x moments evaluated at once (32 MB of doubles)


def chunked(f, x, m):
    """f over the flattened points x in chunks of CHUNK_ENTRIES / m, reshaped like x (the
    (points x moments) table of thousands of moments would not fit otherwise)."""
    x = np.asarray(x, dtype=float)
    flat = x.ravel()
    step = max(1, CHUNK_ENTRIES // max(m, 1))
    out = np.concatenate([f(flat[i:i + step]) for i in range(0, len(flat), step)]) \
        if len(flat) else np.empty(0)
    return out.reshape(x.shape)


def cumulative(mu, x):
    """Jackson-damped Chebyshev cumulative F(x) on [-1, 1] (RMP Eq. 70 integrated)."""
    g = jackson(len(mu)) * mu
    n = np.arange(1, len(mu))

    def one(xs):
        theta = np.arccos(np.clip(xs, -1.0, 1.0))
        s = g[0] * theta + 2.0 * np.sum(g[1:] * np.sin(np.multiply.outer(theta, n)) / n,
                                        axis=-1)
        return 1.0 - s / np.pi
    return chunked(one, x, len(mu))


def density_x(mu, x):
    """Jackson-damped Chebyshev density rho(x) on (-1, 1) (RMP Eq. 70)."""
    g = jackson(len(mu)) * mu
    n = np.arange(1, len(mu))

    def one(xs):
        xs = np.clip(xs, -1.0 + 1e-15, 1.0 - 1e-15)
        theta = np.arccos(xs)
        s = g[0] + 2.0 * np.sum(g[1:] * np.cos(np.multiply.outer(theta, n)), axis=-1)
        return s / (np.pi * np.sqrt(1.0 - xs * xs))
    return chunked(one, x, len(mu))


def moments(A, d, n_modes, kind="full", n_moments=256, n_probes=16, *, seed=0,
            probe_kind="rademacher", bounds=None, lanczos_steps=40, margin=1e-3, progress=None,
            keys=None):
    """KPM moments of the spectral density of the distributed matrix A (non-rattler rows, blocks
    of d; translations projected out).  ``bounds`` = (a, b) skips the Lanczos estimate;
    ``keys`` (particle ids of the local rows) make the probes independent of the numbering."""

    if n_moments < 2:
        raise ParjamError(f"--moments must be >= 2, got {n_moments}")
    if n_probes < 1:
        raise ParjamError(f"--probes must be >= 1, got {n_probes}")
    if probe_kind not in PROBES:
        raise ParjamError(f"unknown probe kind {probe_kind!r}; choose from {', '.join(PROBES)}")
    log = progress or (lambda msg: None)
    t0 = time.perf_counter()
    with log_stage("kpm: bounds"):
        if bounds is None:
            a, b, info = spectral_bounds(A, d, kind, seed, lanczos_steps, margin, keys)
        else:
            a, b = (float(x) for x in bounds)
            if not (np.isfinite(a) and np.isfinite(b) and a < b):
                raise ParjamError(f"KPM bounds need a < b, got {bounds}")
            info = {"bounds": "given"}
    c, h = 0.5 * (a + b), 0.5 * (b - a)
    log(f"kpm: {kind} matrix, {A.getSize()[0]} dof, spectrum in [{a:.4g}, {b:.4g}], "
        f"{n_moments} moments x {n_probes} probes")
    raw = np.zeros((n_probes, n_moments))
    r = A.createVecRight()
    with log_stage("kpm: moments"):
        for p in range(n_probes):
            fill_probe(r, seed, p, probe_kind, keys=keys)
            translations.project(r, d)
            raw[p] = probe_moments(A, r, c, h, n_moments)
            if (p + 1) % max(1, n_probes // 2) == 0:
                log(f"kpm: probe {p + 1}/{n_probes}")
    r.destroy()
    check_inside(raw, a, b)
    per_probe = raw / n_modes
    mu = per_probe.mean(axis=0)
    mu[0] = 1.0  # the exact trace of P; the probes' own mu_0 is in probe_moments
    info.update({"a": a, "b": b, "matvecs": n_probes * ((n_moments + 1) // 2),
                 "probe_mu0_mean": float(per_probe[:, 0].mean())})
    return KPMResult(moments=mu, probe_moments=per_probe, a=a, b=b, n_modes=int(n_modes),
                     matrix=kind, probe_kind=probe_kind, seed=int(seed), info=info,
                     seconds=time.perf_counter() - t0)


def check_inside(raw, a, b):
    """|r^T T_n(A~) r| <= |r|^2 holds for every n iff the spectrum lies in [a, b]; growth beyond
    round-off means an eigenvalue outside (e.g. an unstable packing below a)."""
    ratio = np.abs(raw) / raw[:, :1]
    if np.any(ratio > 1.0 + ROUNDOFF):
        n = int(np.argmax(ratio.max(axis=0) > 1.0 + ROUNDOFF))
        raise ParjamError(f"KPM: Chebyshev moments grow (|mu_{n}| > mu_0): an eigenvalue lies "
                          f"outside the bounds [{a:.4g}, {b:.4g}] (unstable packing with "
                          f"negative modes?); give wider --kpm-bounds")


# --- D(omega), D0, omega* -----------------------------------------------------------------------
def dos_summary(res, plateau=None, grid=4096):
    """(D0, omega*, plateau window) from the KPM cumulative with the definitions of
    parjam.vib.observables: D0 the mean density over the window (default the 30 % and 60 %
    frequency quantiles), omega* half the first omega where N(omega) / omega >= D0 / 2."""
    w = np.linspace(0.0, res.omega_max, grid + 1)[1:]
    N = res.cumulative(w * w)
    N = np.maximum.accumulate(np.clip(N - res.weight_below_zero, 0.0, None))  # monotone, from 0
    if plateau is None:
        w1 = float(np.interp(0.3, N, w))
        w2 = float(np.interp(0.6, N, w))
    else:
        w1, w2 = plateau
    if not 0 <= w1 < w2:
        raise ParjamError(f"plateau window needs 0 <= w1 < w2, got {w1}, {w2}")
    d0 = float((np.interp(w2, w, N) - np.interp(w1, w, N)) / (w2 - w1))
    hit = np.nonzero(N / w >= 0.5 * d0)[0]
    wstar = float(w[hit[0]] / 2.0) if len(hit) and d0 > 0 else float("nan")
    return d0, wstar, (w1, w2)


def dos_record(res, bins=40, omega_max=None, plateau=None):
    """D(omega) on linear bins [0, omega_max] with its probe error, D0 and omega*, in the layout
    of parjam.vib.observables.dos_record."""
    top = omega_max or res.omega_max
    edges = observables.dos_edges(top, bins)
    density, err = res.binned_with_error(edges)
    d0, wstar, window = dos_summary(res, plateau)
    return {"omega": 0.5 * (edges[1:] + edges[:-1]), "edges": edges, "density": density,
            "density_error": err, "binning": "linear",
            "normalisation": "per mode: KPM fraction of the d N' - d modes per bin / bin width",
            "n_modes_total": int(res.n_modes), "D0": d0, "omega_star": wstar,
            "plateau_window": np.array(window, dtype=float)}


def compute(comm, system, kind="full", n_moments=256, n_probes=16, seed=0,
            probe_kind="rademacher", bounds=None, progress=None):
    """KPM moments of one matrix of an ActiveSystem (parjam.vib.spectrum): assemble, run, free."""
    A = spectrum.dynamical_matrix(comm, system, kind, fmt="aij")
    try:
        return moments(A, system.d, system.n_modes, kind, n_moments, n_probes, seed=seed,
                       probe_kind=probe_kind, bounds=bounds, progress=progress,
                       keys=system.ids)
    finally:
        A.destroy()


def l1_distance(density_a, density_b, edges):
    """L1 distance sum |D_a - D_b| * width of two per-mode densities on the same bins (0 .. 2)."""
    return float(np.sum(np.abs(np.asarray(density_a) - np.asarray(density_b)) * np.diff(edges)))
