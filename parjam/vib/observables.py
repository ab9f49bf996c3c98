"""Observables of vibrational spectra: the density of states D(omega), its plateau D0 and the
onset frequency omega*, and per-mode participation ratios and transverse/longitudinal sums.

Conventions (docs/howto/spectra.md):

- frequencies omega = sign(lambda) sqrt|lambda| of the eigenvalues lambda = omega^2 (unit masses);
- D(omega) is normalised *per mode*: counts / (n_modes * bin width) with n_modes = d N' - d, the
  number of non-translational modes of the whole spectrum, so that a partial spectrum (the k lowest
  modes) gives the same D(omega) as the full one on the range it covers, and the full D(omega)
  integrates to 1 (the paper's "number of modes per unit frequency", per mode);
- D0, the plateau height: the mean density of modes over a plateau window [w1, w2],
  (N(w2) - N(w1)) / (n_modes (w2 - w1)) with N the cumulative count.  Default window: for a
  complete spectrum the 30 % and 60 % frequency quantiles; for the k lowest modes the upper half
  [omega_k / 2, omega_k] of the computed range;
- omega*: with the mean density below omega, m(omega) = N(omega) / (n_modes omega), let
  omega_half be the smallest mode frequency with m(omega) >= D0 / 2; omega* = omega_half / 2.
  For a step D = D0 theta(omega - omega*) this returns omega* exactly; it uses the cumulative count
  only, so it needs no binning.
"""

import numpy as np

from parjam.errors import ParjamError


def frequency(eigenvalue):
    """omega = sign(lambda) sqrt|lambda|: negative for unstable directions."""
    lam = np.asarray(eigenvalue, dtype=float)
    return np.sign(lam) * np.sqrt(np.abs(lam))


def n_modes_total(n_active, d):
    """Non-translational modes of the deflated dynamical matrix: d N' - d."""
    return d * n_active - d


# --- per-mode observables (dense vectors, shape (K, N', d)) -------------------------------------
def participation_ratio(vectors):
    """P = (sum_i |e_i|^2)^2 / (N' sum_i |e_i|^4) for each mode (1 extended, ~1/N' localised)."""
    v = np.asarray(vectors)
    w = np.einsum("kia,kia->ki", v, v)
    return w.sum(axis=1) ** 2 / (v.shape[1] * np.einsum("ki,ki->k", w, w))


def unit_blocks(rij, r, part):
    """Per-contact blocks n n^T ("par") or I - n n^T ("perp"): v^T A v assembled from them is
    sum_<ij> of the squared longitudinal / transverse relative displacement."""
    n = rij / r[:, None]
    nn = n[:, :, None] * n[:, None, :]
    if part == "par":
        return nn
    if part == "perp":
        return np.eye(rij.shape[1])[None] - nn
    raise ValueError(f"part must be 'par' or 'perp', got {part!r}")


TRANS_BLOCK_VALUES = 1 << 21  # doubles of one block of relative displacements (16 MB)


def transverse_longitudinal(vectors, i, j, rij, r):
    """The paper's Fig. "trans" sums for each mode (unit-normalised vectors):
    eps_perp = 1/2 sum_<ij> [(dR_j - dR_i)_perp]^2, eps_par = 1/2 sum_<ij> [(dR_j - dR_i).n_ij]^2."""
    v = np.asarray(vectors)
    n = rij / r[:, None]
    perp, par = np.empty(len(v)), np.empty(len(v))
    # a block of modes at a time: the relative displacements of all modes at once are
    # k x Nc x d (250 MB for the 3000 modes of N = 1024, allocated twice), a block ~16 MB
    step = max(1, TRANS_BLOCK_VALUES // max(1, len(i) * v.shape[-1]))
    for a in range(0, len(v), step):
        rel = v[a:a + step, j, :] - v[a:a + step, i, :]
        p = np.einsum("kca,ca->kc", rel, n)
        total = np.einsum("kca,kca->kc", rel, rel)
        perp[a:a + step] = 0.5 * (total - p**2).sum(axis=1)
        par[a:a + step] = 0.5 * (p**2).sum(axis=1)
    return perp, par


# --- density of states ---------------------------------------------------------------------------
def dos_edges(omega_max, bins=40, log=False, omega_min=None):
    """Bin edges on [0, omega_max] (linear) or [omega_min, omega_max] (log)."""
    if not np.isfinite(omega_max) or omega_max <= 0:
        raise ParjamError("the density of states needs positive frequencies")
    if bins < 1:
        raise ParjamError(f"the number of bins must be >= 1, got {bins}")
    if not log:
        return np.linspace(0.0, omega_max, bins + 1)
    lo = omega_min if omega_min else omega_max * 1e-3
    if not 0 < lo < omega_max:
        raise ParjamError(f"log bins need 0 < omega_min < omega_max, got {lo}, {omega_max}")
    return np.geomspace(lo, omega_max, bins + 1)


def density_of_states(omega, n_modes, edges):
    """D(omega) per mode on the given edges: counts / (n_modes * width); returns (centres, D).
    Centres are arithmetic for linear bins and geometric for log bins."""
    omega = np.asarray(omega, dtype=float)
    counts, _ = np.histogram(omega, bins=edges)
    width = np.diff(edges)
    log = edges[0] > 0 and np.allclose(edges[1:] / edges[:-1], edges[1] / edges[0])
    centres = np.sqrt(edges[1:] * edges[:-1]) if log else 0.5 * (edges[1:] + edges[:-1])
    return centres, counts / (n_modes * width)


def cumulative(omega, n_modes, at):
    """N(at) / n_modes: the fraction of all modes with frequency <= at."""
    s = np.sort(np.asarray(omega, dtype=float))
    return np.searchsorted(s, at, side="right") / n_modes


def default_plateau(omega, n_modes):
    """Plateau window (see module doc): quantiles of a complete spectrum, or the upper half of
    the computed range of a partial one."""
    w = np.sort(np.asarray(omega, dtype=float))
    w = w[w > 0]
    if len(w) == 0:
        raise ParjamError("no positive frequencies: no plateau")
    if len(w) >= n_modes:
        return float(np.quantile(w, 0.3)), float(np.quantile(w, 0.6))
    return 0.5 * float(w[-1]), float(w[-1])


def plateau_height(omega, n_modes, window=None):
    """D0: mean density of modes over the plateau window [w1, w2]."""
    w1, w2 = window or default_plateau(omega, n_modes)
    if not 0 <= w1 < w2:
        raise ParjamError(f"plateau window needs 0 <= w1 < w2, got {w1}, {w2}")
    return float((cumulative(omega, n_modes, w2) - cumulative(omega, n_modes, w1)) / (w2 - w1))


def omega_star(omega, n_modes, d0):
    """omega* = omega_half / 2, omega_half the first mode frequency where N(omega)/(n omega)
    reaches d0 / 2 (exact onset for a step-shaped D(omega)); NaN if never reached."""
    w = np.sort(np.asarray(omega, dtype=float))
    w = w[w > 0]
    if len(w) == 0 or not d0 > 0:
        return float("nan")
    # N(omega) just at each mode frequency (ties count fully), over n_modes omega
    mean_density = cumulative(w, n_modes, w) / w
    hit = np.nonzero(mean_density >= 0.5 * d0)[0]
    return float(w[hit[0]] / 2.0) if len(hit) else float("nan")


def dos_summary(omega, n_modes, plateau=None):
    """(D0, omega*, plateau window) of one spectrum."""
    window = plateau or default_plateau(omega, n_modes)
    d0 = plateau_height(omega, n_modes, window)
    return d0, omega_star(omega, n_modes, d0), window


def ensemble_mean(values):
    """Mean and standard error of the mean over the first axis (error 0 for one sample)."""
    a = np.asarray(values, dtype=float)
    mean = np.nanmean(a, axis=0)
    n = np.sum(np.isfinite(a), axis=0)
    err = np.nanstd(a, axis=0, ddof=1) / np.sqrt(n) if a.shape[0] > 1 else np.zeros_like(mean)
    return mean, err


MAX_AUTO_BINS = 40


def auto_bins(n_frequencies):
    """Bins for ``n`` computed frequencies when none are asked for: about sqrt(n), between 3 and
    40, so that a few lowest modes (``--k 20``) give a histogram rather than a comb of bins
    holding 0 or 1 mode."""
    return int(min(MAX_AUTO_BINS, max(3, round(np.sqrt(n_frequencies)))))


def dos_record(omega, n_modes, bins=None, log=False, omega_min=None, plateau=None):
    """D(omega) of one spectrum on bins up to its highest computed frequency (``bins`` None:
    :func:`auto_bins`), with D0 and omega* (definitions above)."""
    pos = np.asarray(omega)[np.asarray(omega) > 0]
    if len(pos) == 0:
        raise ParjamError("no positive frequency: cannot build D(omega)")
    bins = auto_bins(len(pos)) if bins is None else bins
    edges = dos_edges(float(pos.max()), bins, log, omega_min)
    centres, density = density_of_states(pos, n_modes, edges)
    d0, wstar, window = dos_summary(pos, n_modes, plateau)
    return {"omega": centres, "edges": edges, "density": density,
            "binning": "log" if log else "linear",
            "normalisation": "per mode: counts / ((d N' - d) * bin width)",
            "n_modes_total": int(n_modes), "D0": d0, "omega_star": wstar,
            "plateau_window": np.array(window, dtype=float),
            "definition": "D0 = mean density over the plateau window; omega* = omega_half / 2, "
                          "omega_half the first frequency where N(omega)/(n omega) >= D0/2"}
