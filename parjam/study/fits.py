"""Fits of the paper's laws to ensemble results, with bootstrap errors over members.

Tables are (members, states) arrays, one row per ensemble member (as in the summary files of
``parjam run``); a bootstrap resample draws whole rows with replacement, so the x and y values
of a member stay together.  The errors therefore cover member-to-member scatter only (not the
choice of fit range or finite-size effects).  An x shared by all members (a protocol's dphi or
pressures) may be given as one row: it is then the same in every resample.
"""

import warnings

import numpy as np

N_BOOT = 2000


def bootstrap(stat, members, n_boot=N_BOOT, seed=0):
    """``stat(rows)`` of all members and of ``n_boot`` resamples of the member indices (drawn
    with replacement from ``default_rng(seed)``): (best, boots) as arrays, boots with one row
    per resample."""
    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():  # all-NaN resamples (a member missing): NaN, no warning
        warnings.simplefilter("ignore", RuntimeWarning)
        boots = np.array([stat(rng.integers(0, members, members)) for _ in range(n_boot)])
        return np.asarray(stat(np.arange(members))), boots


def log_slope(x, y):
    """(slope, log prefactor) of the least-squares line through (log x, log y)."""
    return np.polyfit(np.log(x), np.log(y), 1)


def fit_power(X, Y, n_boot=N_BOOT, seed=0):
    """Power law mean(Y) = a mean(X)^b over the states (columns), means over members (rows,
    NaN skipped), points with a non-positive mean left out; X and Y resampled together (X may
    be one row shared by all members).  Returns exponent, its bootstrap error, prefactor and
    its error, members and points."""
    Y = np.asarray(Y, float)
    X = np.broadcast_to(np.asarray(X, float), Y.shape)

    def one(rows):
        x, y = np.nanmean(X[rows], axis=0), np.nanmean(Y[rows], axis=0)
        ok = (x > 0) & (y > 0)
        if ok.sum() < 2:
            return np.nan, np.nan
        b, a = log_slope(x[ok], y[ok])
        return b, np.exp(a)

    (b, a), boots = bootstrap(one, len(X), n_boot, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        b_err, a_err = np.nanstd(boots[:, 0]), np.nanstd(boots[:, 1])
    return {"exponent": float(b), "exponent_err": float(b_err),
            "prefactor": float(a), "prefactor_err": float(a_err),
            "members": int(len(X)), "points": int(X.shape[1])}


def fit_eq33(W2, WS2, DZ, P, n_boot=N_BOOT, seed=0):
    """Eq. (33), omega_AM^2 = A1 dz^2 - A2 p.  Along a compression dz^2 and p are proportional
    (Eq. 22), so a joint fit cannot separate A1 from A2; instead A1 comes from the relaxed
    system, omega*_relaxed^2 = A1 dz^2 (no pressure term), and A2 per state from
    (A1 dz^2 - omega_AM^2) / p, A2 their mean.  W2 = omega_AM^2 (full system), WS2 =
    omega*_relaxed^2, DZ, P: (members, states) tables; bootstrap errors over members."""
    def one(rows):
        w2, ws2, dz, p = (np.nanmean(a[rows], axis=0) for a in (W2, WS2, DZ, P))
        a1 = np.sum(ws2 * dz**2) / np.sum(dz**4)
        a2 = (a1 * dz**2 - w2) / p
        return np.concatenate([[a1, np.mean(a2)], a2])

    best, boots = bootstrap(one, len(W2), n_boot, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        err = np.nanstd(boots, axis=0)
    return {"A1": float(best[0]), "A1_err": float(err[0]), "A2": float(best[1]),
            "A2_err": float(err[1]), "A2_per_state": [float(x) for x in best[2:]],
            "A2_per_state_err": [float(x) for x in err[2:]]}


def law(fit):
    """'exponent +- error' of a fit_power result."""
    return f"{fit['exponent']:.3f} +- {fit['exponent_err']:.3f}"
