"""Has a symmetric matrix an eigenvalue below -s?  A Lanczos test in O(N/P) memory, with a
certificate for either answer: the stability check of the packing protocol (parjam.pack.stability)
without a factorisation.

The matrix A is a dynamical matrix of Eq. (1) on N' particles (blocks of d rows per particle,
distributed by block rows), whose d uniform translations T are exact zero modes.  The test runs
the Lanczos recurrence of A on the complement of T (every product projected off T, one
exact sum of d numbers) from a pseudo-random start, without reorthogonalisation: three vectors of
this rank's rows, plus a fourth to rebuild a Ritz vector.  After k steps it holds the tridiagonal
T_k (alpha_1..alpha_k, beta_1..beta_k, beta_k the residual norm) and decides:

- **below** (an eigenvalue of A lies below -s): once the lowest Ritz value theta and its
  residual bound r = beta_k |y_k| satisfy theta + r < -WITNESS_MARGIN s, its Ritz vector x is
  rebuilt by a second pass of the same recurrence, projected off T, and its Rayleigh quotient
  x^T A x / x^T x, computed from A itself, must lie below -WITNESS_MARGIN s too.  By
  Courant-Fischer lambda_min <= that quotient: a certificate that needs no probability.  Asked
  for a vector, the recurrence first goes on until the Ritz pair has converged, and x is the
  direction in which the packing leaves the saddle.
- **not below** (no eigenvalue below -s): every Ritz value lies above -s and the start vector's
  component along any eigenvector with an eigenvalue mu <= -s is at most

      tau_k = (beta_1 ... beta_k) / det(T_k + s I),

  because the Lanczos vector v_{k+1} = chi_k(A) v_1 / (beta_1 ... beta_k), chi_k the
  characteristic polynomial of T_k, has norm 1 and |chi_k(mu)| >= det(T_k + s I) for mu <= -s
  when all Ritz values exceed -s (van Dorsselaer, Hochstenbach & van der Vorst, SIAM J. Matrix
  Anal. Appl. 22, 837 (2000): the Lanczos-polynomial bound).  For a start uniform on the unit
  sphere of the n = dN' - d dimensional complement of T, P(|q^T v_1| <= tau) <= tau sqrt(2n/pi)
  for any fixed unit q, so the test says "not below" only when tau_k sqrt(2n/pi) <= delta: the
  probability that it misses an eigenvalue below -s is at most delta (default 1e-10).  The
  pivots d_i of T_k + s I (one per step, d_i = alpha_i + s - beta_{i-1}^2 / d_{i-1}) give both
  the number of Ritz values below -s (Sylvester, on the tridiagonal) and log det, so the bound
  costs nothing per step.
- **inconclusive**: neither within the step budget, a lowest Ritz value that converges inside
  the round-off band (-WITNESS_MARGIN s, 0] where neither answer can be trusted, or a witness
  whose recomputed Rayleigh quotient is not below -WITNESS_MARGIN s.  The caller decides what
  then (parjam.pack.stability: the exact inertia where it fits).

The start vector is a function of the particles' global ids only (a counter-based hash, Box-
Muller), the same on any number of ranks and independent of the positions; the probability is
over that draw.  Every sum of the recurrence (the projections, alpha_j, beta_j, the Rayleigh
quotient) is exact (parjam.net.exactsum) and the product is taken in an order of global ids
(parjam.vib.rowproduct), so the steps, the verdict and the vector are the same bits on any
number of ranks: a packing that leaves a saddle along that vector does so on 1 or P ranks
alike.  The bound is an exact-arithmetic statement; in floating point the recurrence
loses orthogonality, which only repeats converged Ritz values (Paige; Greenbaum, Linear Algebra
Appl. 113, 7 (1989)) and does not weaken the extreme ones.

The number of steps is set by the lowest eigenvalue lambda_1 against the spectrum's width c:
about ln(sqrt(2n/pi)/delta) / (2 sqrt(lambda_1 / c)) for a stable state (docs/results/stability.md).
"""

from dataclasses import dataclass

import numpy as np

from parjam import env
from parjam.errors import ParjamError
from parjam.net import exactsum

WITNESS_MARGIN = 2.0  # "below" needs a Rayleigh quotient <= -2 s: s of margin for its round-off
DELTA = 1e-10  # probability bound of a missed eigenvalue below -s
MAX_STEPS = 40000  # step budget (each one product with A)
CHECK_EVERY = 25  # steps between evaluations of the lowest Ritz pair (when one lies below -s)
RTOL = 1e-6  # a Ritz pair has converged when its residual bound is RTOL |theta|
FLOOR = 0.01  # ... or FLOOR s (= eps ||A||: the round-off floor of a residual)
OPTIONS = "lanczos_"  # sub-prefix of the caller's options prefix

BELOW, NOT_BELOW, INCONCLUSIVE = 1, 0, -1


@dataclass
class LanczosResult:
    """Outcome of ``lowest_test``."""

    verdict: int  # BELOW, NOT_BELOW or INCONCLUSIVE
    steps: int  # Lanczos steps (products with A) of the first pass
    lowest: float  # lowest Ritz value (or the witness's Rayleigh quotient when BELOW)
    residual: float  # its residual bound (or the witness's true residual norm)
    n_below: int  # distinct converged Ritz values below -s (a lower bound on the count)
    failure: float  # bound on the probability of a missed eigenvalue below -s (NOT_BELOW)
    vector: np.ndarray = None  # this rank's rows of the unit witness / lowest Ritz vector
    why: str = ""


@dataclass
class Settings:
    delta: float = DELTA
    max_steps: int = MAX_STEPS
    check_every: int = CHECK_EVERY
    rtol: float = RTOL
    seed: int = 0x5AB1E

    @classmethod
    def from_options(cls, prefix):
        """The defaults, overridden by -<prefix>lanczos_{delta,max_it,check_every,rtol,seed}
        (the test's setFromOptions); values that cannot work are a ParjamError."""
        opts = env.petsc().Options(prefix + OPTIONS)
        d = cls()
        s = cls(delta=opts.getReal("delta", d.delta), max_steps=opts.getInt("max_it", d.max_steps),
                check_every=opts.getInt("check_every", d.check_every),
                rtol=opts.getReal("rtol", d.rtol), seed=opts.getInt("seed", d.seed))
        name = f"-{prefix}{OPTIONS}"
        for ok, what in ((0.0 < s.delta < 1.0, f"{name}delta {s.delta:g}: must lie in (0, 1)"),
                         (s.max_steps >= 1, f"{name}max_it {s.max_steps}: must be >= 1"),
                         (s.check_every >= 1, f"{name}check_every {s.check_every}: must be >= 1"),
                         (0.0 < s.rtol < 1.0, f"{name}rtol {s.rtol:g}: must lie in (0, 1)"),
                         (s.seed >= 0, f"{name}seed {s.seed}: must be >= 0")):
            if not ok:
                raise ParjamError(what)
        return s


def _mix(z):
    """splitmix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def start_rows(ids, d, seed):
    """Standard normal numbers for the d components of the particles ``ids`` (global ids): a
    function of (seed, id, component) only, so any distribution of the rows gives the same
    vector."""
    ids = np.asarray(ids, dtype=np.uint64)
    key = ids[:, None] * np.uint64(2 * d) + np.arange(2 * d, dtype=np.uint64)[None, :]
    with np.errstate(over="ignore"):
        bits = _mix(key + np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15))
    u = ((bits >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)  # (0, 1)
    u1, u2 = u[:, :d], u[:, d:]
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


class _Recurrence:
    """The projected Lanczos recurrence on this rank's rows (see the module doc): three numpy
    vectors, and per step one product with the operator and two exact sums over the ranks
    (parjam.net.exactsum: d + 1 numbers, then one), so every number it makes is the same bits
    on any number of ranks when the product is (parjam.vib.rowproduct)."""

    def __init__(self, op, d, start):
        self.op, self.d = op, d
        self.mpi = op.mpi
        self.n_part = op.n
        v = np.array(start, dtype=np.float64).reshape(-1)
        self.project(v)
        v /= self.norm(v)
        self.v, self.p = v, np.zeros_like(v)
        self.beta = 0.0

    def project(self, arr):
        """arr <- arr - T T^T arr (in place)."""
        cols = arr.reshape(-1, self.d)
        tot = exactsum.totals(self.mpi, *(cols[:, a] for a in range(self.d)))
        cols -= np.array(tot) / self.n_part

    def norm(self, arr):
        return float(np.sqrt(exactsum.fsum(self.mpi, arr * arr)))

    def step(self):
        """One step: returns (alpha_j, beta_j) and moves on to v_{j+1}."""
        v = self.v
        w = self.op.apply(v)
        cols = w.reshape(-1, self.d)
        sums = exactsum.totals(self.mpi, *(cols[:, a] for a in range(self.d)), v * w)
        cols -= np.array(sums[:self.d]) / self.n_part  # P A v; v is off T: v.(P A v) = v.(A v)
        alpha = float(sums[self.d])
        w -= alpha * v
        if self.beta:
            w -= self.beta * self.p
        beta = self.norm(w)
        if beta > 0.0:
            w *= 1.0 / beta
        self.v, self.p = w, v
        self.beta = beta
        return alpha, beta


def _lowest_pair(alphas, betas):
    """The lowest Ritz value of T_k, its residual bound beta_k |y_k| and its eigenvector y."""
    from scipy.linalg import eigh_tridiagonal

    a, b = np.asarray(alphas), np.asarray(betas)
    k = len(a)
    if k == 1:
        return float(a[0]), abs(float(b[0])), np.ones(1)
    theta, y = eigh_tridiagonal(a, b[:k - 1], select="i", select_range=(0, 0))
    return float(theta[0]), abs(float(b[k - 1] * y[k - 1, 0])), y[:, 0]


def _distinct_below(alphas, betas, level, s):
    """Distinct converged Ritz values below ``level``: those whose residual interval lies below
    it, the copies that a recurrence without reorthogonalisation makes of a converged value
    (its ghosts) merged with it when they lie within their residual bounds plus s (round-off)."""
    from scipy.linalg import eigh_tridiagonal

    a, b = np.asarray(alphas), np.asarray(betas)
    k = len(a)
    if k == 1:
        return int(a[0] + abs(b[0]) < level)
    off = np.abs(b[:k - 1])
    floor = float(np.min(a - np.concatenate([[0.0], off]) - np.concatenate([off, [0.0]])))
    if floor >= level:
        return 0
    theta, y = eigh_tridiagonal(a, b[:k - 1], select="v", select_range=(floor - 1.0, level))
    res = np.abs(b[k - 1] * y[k - 1, :])
    count, last = 0, None
    for t, r in zip(theta, res):
        if t + r >= level:
            continue
        if last is None or t - last[0] > last[1] + r + s:
            count += 1
        last = (t, r)
    return count


def _rebuild(op, d, start, y):
    """The Ritz vector sum_i y_i v_i by a second pass of the same recurrence (a new array)."""
    rec = _Recurrence(op, d, start)
    x = np.zeros_like(rec.v)
    for i in range(len(y)):
        x += y[i] * rec.v
        if i + 1 < len(y):
            rec.step()
    rec.project(x)
    return x


def rayleigh(op, x, d):
    """(x^T A x / x^T x, ||A x - rho x|| / ||x||) with A x projected off the translations
    (exact sums: the same bits on any number of ranks when the product is)."""
    mpi = op.mpi
    aa = op.apply(x)
    cols = aa.reshape(-1, d)
    tot = exactsum.totals(mpi, *(cols[:, a] for a in range(d)))
    cols -= np.array(tot) / op.n
    xx, xax = exactsum.totals(mpi, x * x, x * aa)
    rho = float(xax / xx)
    r = aa - rho * x
    res = float(np.sqrt(exactsum.fsum(mpi, r * r) / xx))
    return rho, res


def lowest_test(op, d, s, start, settings=None, want_vector=False):
    """Decide whether the symmetric operator ``op`` (translations deflated) has an eigenvalue
    below -s (s > 0), from ``start`` (this rank's rows, e.g. ``start_rows``); see the module
    doc.  ``op`` gives ``apply(v)`` (the product on this rank's rows, a numpy array), ``mpi``
    (its mpi4py communicator) and ``n`` (the number of particles): e.g.
    parjam.vib.rowproduct.HalfEdgeProduct.  The
    test stops at its verdict; a BELOW answer comes with its witness (a Ritz vector with a
    quotient below -2 s, not necessarily an eigenvector).  With ``want_vector`` the recurrence
    goes on until the lowest Ritz pair has converged (residual bound RTOL |theta|, or at the
    round-off floor) and returns that vector with either answer: the direction a packing leaves
    a saddle along.  Collective on A's communicator."""
    st = settings or Settings()
    n_dim = op.n * d - d
    log_sphere = 0.5 * np.log(2.0 * max(n_dim, 1) / np.pi)
    log_delta = np.log(st.delta)
    rec = _Recurrence(op, d, start)
    alphas, betas = [], []
    piv, log_tau, n_neg = 1.0, 0.0, 0
    verdict, why, pair = None, "", None
    band = -WITNESS_MARGIN * s
    for k in range(1, st.max_steps + 1):
        a, b = rec.step()
        alphas.append(a)
        betas.append(b)
        # pivot k of T_k + s I: the Sturm count of the Ritz values below -s, and log det
        piv = a + s - (betas[-2] ** 2 / piv if k > 1 else 0.0)
        if piv == 0.0:
            piv = -np.finfo(np.float64).eps * (abs(a) + s)
        n_neg += piv < 0.0
        log_tau += (np.log(b) if b > 0.0 else -np.inf) - np.log(abs(piv))
        invariant = b <= 1e-14 * max(abs(a), 1.0)
        exhausted = invariant or k == st.max_steps
        due = k % st.check_every == 0 or exhausted
        if verdict == NOT_BELOW and n_neg > 0:
            verdict = None  # a Ritz value went below -s after all: decide again
        if verdict is None:
            if n_neg == 0:
                if log_tau + log_sphere <= log_delta or invariant:
                    verdict = NOT_BELOW
                elif exhausted:
                    low = _lowest_pair(alphas, betas)
                    why = (f"step budget of {st.max_steps} exhausted (lowest Ritz value "
                           f"{low[0]:.3e}, failure bound "
                           f"{np.exp(min(log_tau + log_sphere, 0.0)):.1e})")
                    break
                else:
                    continue
            elif due:
                pair = _lowest_pair(alphas, betas)
                theta, res = pair[0], pair[1]
                if theta + res < band:
                    verdict = BELOW
                elif band <= theta - res and theta + res <= 0.0:
                    why = (f"lowest Ritz value {theta:.3e} converged inside the round-off "
                           f"band [{band:.2e}, 0]")
                    break
                elif exhausted:
                    why = (f"step budget of {st.max_steps} exhausted (lowest Ritz value "
                           f"{theta:.3e} +- {res:.1e})")
                    break
                else:
                    continue
            else:
                continue
            if not want_vector:
                break
        if due or exhausted or pair is None or len(pair[2]) != k:
            pair = _lowest_pair(alphas, betas)
            if pair[1] <= max(st.rtol * abs(pair[0]), FLOOR * s) or exhausted:
                break
    steps = len(alphas)
    failure = float(np.exp(min(log_tau + log_sphere, 0.0))) if n_neg == 0 else 1.0
    if verdict != BELOW and not want_vector:
        low = _lowest_pair(alphas, betas)
        if verdict is None:
            return LanczosResult(INCONCLUSIVE, steps, low[0], low[1], 0, 1.0, None,
                                 why or "no decision")
        return LanczosResult(NOT_BELOW, steps, low[0], low[1], 0, failure)
    if pair is None or len(pair[2]) != steps:
        pair = _lowest_pair(alphas, betas)
    theta, res, y = pair
    x = _rebuild(op, d, start, y)
    rho, true_res = rayleigh(op, x, d)
    vec = x / np.sqrt(exactsum.fsum(op.mpi, x * x))
    if verdict == BELOW:
        if rho > band:
            return LanczosResult(INCONCLUSIVE, steps, rho, true_res, 0, 1.0, None,
                                 f"witness Rayleigh quotient {rho:.3e} not below {band:.2e} "
                                 f"(Ritz value {theta:.3e})")
        return LanczosResult(BELOW, steps, rho, true_res,
                             max(1, _distinct_below(alphas, betas, -s, s)), 1.0, vec)
    if verdict is None:  # asked for a vector: the lowest Ritz vector all the same
        return LanczosResult(INCONCLUSIVE, steps, rho, true_res, 0, 1.0, vec,
                             why or "no decision")
    return LanczosResult(NOT_BELOW, steps, rho, true_res, 0, failure, vec)
