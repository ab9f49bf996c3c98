"""Longitudinal and transverse dynamical structure factors of the eigenmodes (Silbert, Liu &
Nagel, PRL 95, 098301 (2005); cited by Wyart et al., PRE 72, 051306, for l_T):

    F_L(k, omega) = (1/N') sum_n |sum_i (k^ . e_n,i) exp(i k . r_i)|^2 delta(omega - omega_n)
    F_T(k, omega) = (1/N') sum_n |sum_i (k^ x e_n,i) exp(i k . r_i)|^2 delta(omega - omega_n)

for unit-normalised eigenvectors e_n (N' non-rattlers, unit masses) on the wavevectors of the
periodic box, k = 2 pi m / L with integer vectors m (one of each pair +-m: e_n is real, so -k
gives the same weights).  In 2D "k^ x e" is the single transverse component; in 3D both
transverse polarisations are summed (|A|^2 - |k^ . A|^2).  With a complete set of modes the
weights of one k sum to 1 - |rho_k|^2 / N'^2 per polarisation, the translations taking the rest.

Wavevectors of equal |m|^2 form a shell; F is averaged over a shell.  The peak of a shell's
F(omega) is found on a Gaussian-smoothed density in log omega (relative width ``smooth``), so a
phonon-like shell whose weight sits in a few nearly degenerate modes peaks at their frequency.
At small k the peaks follow omega_L,T = c_L,T k; the k at which the transverse peak reaches
omega* gives l_T = 1 / k (the wavelength over 2 pi) numerically.
"""

from dataclasses import dataclass

import numpy as np

from parjam.errors import ParjamError


def wavevector_indices(L, d, k_max):
    """Integer vectors m != 0 with |2 pi m / L| <= k_max, one of each +-m pair (the first
    nonzero component positive), sorted by |m|^2."""
    m_max = int(np.floor(k_max * L / (2.0 * np.pi)))
    if m_max < 1:
        raise ParjamError(f"k_max = {k_max:g} is below the smallest wavevector 2 pi / L = "
                          f"{2 * np.pi / L:.4g} of the box")
    rng = np.arange(-m_max, m_max + 1)
    grid = np.stack(np.meshgrid(*([rng] * d), indexing="ij"), axis=-1).reshape(-1, d)
    m2 = (grid * grid).sum(axis=1)
    first = np.array([row[np.flatnonzero(row)[0]] if m2[k] else 0 for k, row in enumerate(grid)])
    keep = (m2 > 0) & (first > 0) & (m2 <= m_max * m_max)
    grid = grid[keep]
    k = 2.0 * np.pi * np.sqrt((grid * grid).sum(axis=1)) / L
    grid = grid[k <= k_max * (1 + 1e-12)]
    order = np.lexsort(((grid * grid).sum(axis=1),))
    return grid[order]


def mode_amplitudes(vectors, pos, kvecs):
    """A_n(k) = sum_i e_n,i exp(i k . r_i): complex (K, M, d) for vectors (M, N', d)."""
    phase = pos @ kvecs.T  # (N', K)
    M, n, d = vectors.shape
    E = vectors.transpose(1, 0, 2).reshape(n, M * d)
    re = (np.cos(phase).T @ E).reshape(len(kvecs), M, d)
    im = (np.sin(phase).T @ E).reshape(len(kvecs), M, d)
    return re + 1j * im


def polarisation_weights(vectors, pos, kvecs, chunk=16, comm=None):
    """Per-mode longitudinal and transverse weights |k^.A|^2 / N' and (|A|^2 - |k^.A|^2) / N',
    each (K, M); computed in chunks of wavevectors to bound memory.  With an mpi4py ``comm``,
    ``vectors`` and ``pos`` are this rank's rows (particles) only: the amplitudes A are sums
    over particles, summed over the ranks by one allreduce per chunk."""
    n = vectors.shape[1] if comm is None else comm.allreduce(vectors.shape[1])
    WL, WT = [], []
    for s in range(0, len(kvecs), chunk):
        kv = kvecs[s:s + chunk]
        A = mode_amplitudes(vectors, pos, kv)
        if comm is not None:
            A, part = np.empty_like(A), np.ascontiguousarray(A)
            comm.Allreduce(part, A)
        khat = kv / np.linalg.norm(kv, axis=1)[:, None]
        a_par = np.einsum("kma,ka->km", A, khat)
        total = np.einsum("kma,kma->km", A, A.conj()).real
        wl = np.abs(a_par) ** 2
        WL.append(wl / n)
        WT.append((total - wl) / n)
    return np.concatenate(WL), np.concatenate(WT)


@dataclass
class StructureFactor:
    """Shell-averaged per-mode weights of F_L and F_T."""

    omega: np.ndarray  # (M,) mode frequencies
    k: np.ndarray  # (S,) shell wavenumbers
    m2: np.ndarray  # (S,) |m|^2 of each shell
    n_vectors: np.ndarray  # (S,) wavevectors (pairs +-k) in each shell
    weight_L: np.ndarray  # (S, M)
    weight_T: np.ndarray  # (S, M)
    L: float

    def binned(self, edges, part):
        """F(k, omega) on frequency bins: (S, B) per unit frequency."""
        w = self.weight_L if part == "L" else self.weight_T
        out = np.zeros((len(self.k), len(edges) - 1))
        idx = np.digitize(self.omega, edges) - 1
        ok = (idx >= 0) & (idx < len(edges) - 1)
        for s in range(len(self.k)):
            out[s] = np.bincount(idx[ok], weights=w[s, ok], minlength=len(edges) - 1)
        return out / np.diff(edges)[None, :]

    def peaks(self, part, smooth=0.05):
        """omega_peak of every shell (NaN where a shell has no weight)."""
        w = self.weight_L if part == "L" else self.weight_T
        return np.array([peak_frequency(self.omega, row, smooth) for row in w])


def compute(vectors, omega, pos, L, k_max, comm=None):
    """Structure factors of the modes ``vectors`` (M, N', d) with frequencies ``omega`` at the
    non-rattler positions ``pos`` (N', d), for the box wavevectors up to ``k_max``.  With an
    mpi4py ``comm``: each rank passes the rows of its own non-rattlers (any split, the same
    modes on every rank) and gets the whole result (collective)."""
    vectors = np.asarray(vectors, dtype=float)
    if vectors.ndim != 3 or vectors.shape[1:] != pos.shape:
        raise ParjamError("eigenvectors and positions do not match: the structure factor needs "
                          "the eigenvectors of the non-rattlers")
    d = pos.shape[1]
    mvec = wavevector_indices(L, d, k_max)
    kvecs = 2.0 * np.pi * mvec / L
    WL, WT = polarisation_weights(vectors, pos, kvecs, comm=comm)
    m2 = (mvec * mvec).sum(axis=1)
    shells, inverse, counts = np.unique(m2, return_inverse=True, return_counts=True)
    SL = np.zeros((len(shells), len(omega)))
    ST = np.zeros_like(SL)
    np.add.at(SL, inverse, WL)
    np.add.at(ST, inverse, WT)
    return StructureFactor(np.asarray(omega, float), 2 * np.pi * np.sqrt(shells) / L, shells,
                           counts, SL / counts[:, None], ST / counts[:, None], L)


def peak_frequency(omega, weight, smooth=0.05, points=2000):
    """Frequency of the maximum of the weights smoothed per unit omega,
    (1/omega) sum_n w_n exp(-(ln omega - ln omega_n - smooth^2)^2 / (2 smooth^2)) (log-normal
    kernels of relative width ``smooth`` with their maxima at the omega_n; positive frequencies
    only), refined by a parabola through the top three grid points."""
    omega = np.asarray(omega, float)
    ok = (omega > 0) & (weight > 0)
    if not ok.any():
        return float("nan")
    lw, w = np.log(omega[ok]), weight[ok]
    grid = np.linspace(lw.min() - 3 * smooth, lw.max() + 3 * smooth, points)
    dens = np.zeros(points)
    for s in range(0, len(lw), 512):
        dens += (w[s:s + 512, None] * np.exp(-0.5 * ((grid[None, :] - lw[s:s + 512, None])
                                                     / smooth) ** 2)).sum(axis=0)
    # kernels centred at ln omega_n + smooth^2: divided by omega (a density per omega, not per
    # ln omega) each is a log-normal whose maximum lies exactly at omega_n
    grid_c = grid + smooth * smooth  # D(x) = K(x - s^2 - ln omega_n) / e^x at x = grid + s^2
    dens /= np.exp(grid_c)
    i = int(np.argmax(dens))
    if 0 < i < points - 1:
        y0, y1, y2 = dens[i - 1:i + 2]
        den = y0 - 2 * y1 + y2
        shift = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        return float(np.exp(grid_c[i] + shift * (grid[1] - grid[0])))
    return float(np.exp(grid_c[i]))


def dispersion_slope(k, omega_peak, k_fit):
    """Slope c of omega = c k through the origin, least squares over shells with k <= k_fit."""
    sel = (k <= k_fit * (1 + 1e-12)) & np.isfinite(omega_peak)
    if not sel.any():
        return float("nan")
    return float((k[sel] * omega_peak[sel]).sum() / (k[sel] ** 2).sum())


def crossing_wavenumber(k, omega_peak, omega_target):
    """The k at which the peak dispersion first reaches omega_target (linear interpolation
    between shells; extrapolated linearly through the origin below the first shell, NaN if
    never reached)."""
    ok = np.isfinite(omega_peak)
    k, w = k[ok], omega_peak[ok]
    if len(k) == 0 or not np.isfinite(omega_target):
        return float("nan")
    if w[0] >= omega_target:
        return float(k[0] * omega_target / w[0])
    above = np.flatnonzero(w >= omega_target)
    if len(above) == 0:
        return float("nan")
    a = above[0]
    t = (omega_target - w[a - 1]) / (w[a] - w[a - 1])
    return float(k[a - 1] + t * (k[a] - k[a - 1]))
