"""D(omega), D0 and omega* of one packing state by KPM (parjam.vib.kpm) for the scenes of
``parjam run`` (``dos = { method = "kpm", ... }``): the number of moments chosen by the
resolution omega* needs, and the moments stored as a record and read back, so that the summary
evaluates D(omega) from them and the plots read results only.

Resolution (docs/results/speed-accuracy.md, "D(omega): dense LAPACK, spectrum slicing, KPM"): the
Jackson kernel smears D(omega) over

    Delta omega = (pi / 2) sqrt(lambda_max) / M    (about 4 / M for 3D harmonic spheres, measured)

uniformly in omega, and KPM's omega* (the onset estimator of parjam.vib.observables) is biased high
until omega* >> Delta omega.  Measured against dense LAPACK at N = 1024
(scripts/check_kpm_dense.py --calibrate, docs/results/reproduction.md section 11): +13 % at
omega*_KPM / Delta omega = 6.5 and -1 .. +3 % from 20 on at dphi = 1e-3; -2 .. -6 % at any
ratio >= 10 at dphi >= 1e-2; but +17 % at 16 and +13 % at 30 at dphi = 1e-4, where the full
matrix's onset is soft.  So omega* counts as **resolved** when omega*_KPM >= RESOLVED x
Delta omega, else it is recorded as NaN (the D(omega) curve and D0, which converge much earlier,
are kept); below dphi ~ 1e-3 the lowest modes with the KPM D0 are the better estimator.
``moments = "auto"``: start at AUTO_START moments and double (the recurrence resumed, so the
cost is that of the final M only) until omega* is resolved or ``max_moments`` is reached.
"""

import time

import numpy as np

from parjam.vib import kpm, spectrum, translations
from parjam.logstage import log_stage

RESOLUTION = np.pi / 2  # Delta omega = RESOLUTION sqrt(lambda_max) / M
RESOLVED = 20.0  # omega*_KPM / Delta omega above which omega* is kept
AUTO_START = 256
SEED = 0  # probe seed of the scenes' KPM (the same probes for every state and member)


def resolution(b, moments):
    """Delta omega of M moments on a spectrum up to lambda_max = b."""
    return RESOLUTION * np.sqrt(max(b, 0.0)) / moments


def summary(res):
    """(D0, omega* or NaN when unresolved, omega*_KPM as computed, plateau window) of a
    KPMResult; the omega grid resolves Delta omega."""
    grid = max(4096, 4 * res.n_moments)
    d0, wstar, window = kpm.dos_summary(res, grid=grid)
    ok = np.isfinite(wstar) and wstar >= RESOLVED * resolution(res.b, res.n_moments)
    return d0, (wstar if ok else np.nan), wstar, window


def adaptive(A, d, n_modes, kind, moments, probes, max_moments, keys=None, progress=None):
    """KPMResult of ``moments`` moments (an int), or for ``moments = "auto"`` of as many as
    resolve omega* (doubling from AUTO_START up to ``max_moments``)."""
    t0 = time.perf_counter()
    a, b, info = kpm.spectral_bounds(A, d, kind, SEED, keys=keys)
    c, h = 0.5 * (a + b), 0.5 * (b - a)
    m = moments if moments != "auto" else min(AUTO_START, max_moments)
    recs = []
    r = A.createVecRight()
    try:
        with log_stage("kpm: moments"):
            for p in range(probes):
                kpm.fill_probe(r, SEED, p, "rademacher", keys=keys)
                translations.project(r, d)
                recs.append(kpm.Recurrence(A, r, c, h))
            while True:
                raw = np.array([x.advance(m) for x in recs])
                res = result(raw, a, b, n_modes, kind, info)
                _, wstar, _, _ = summary(res)
                if moments != "auto" or np.isfinite(wstar) or m >= max_moments:
                    break
                m = min(2 * m, max_moments)
                if progress:
                    progress(f"kpm {kind}: omega* unresolved, {m} moments")
    finally:
        r.destroy()
        for x in recs:
            x.destroy()
    res.seconds = time.perf_counter() - t0
    return res


def result(raw, a, b, n_modes, kind, info):
    """A KPMResult of raw probe sums (probes x moments), checked to lie inside [a, b]."""
    kpm.check_inside(raw, a, b)
    per_probe = raw / n_modes
    mu = per_probe.mean(axis=0)
    mu[0] = 1.0  # the exact trace of the projector off the translations
    return kpm.KPMResult(moments=mu, probe_moments=per_probe, a=a, b=b, n_modes=int(n_modes),
                         matrix=kind, probe_kind="rademacher", seed=SEED, info=dict(info))


def compute(comm, system, kind, moments, probes, max_moments, progress=None):
    """KPM of one matrix of an ActiveSystem (parjam.vib.spectrum): assemble, run, free."""
    A = spectrum.dynamical_matrix(comm, system, kind, fmt="aij")
    try:
        return adaptive(A, system.d, system.n_modes, kind, moments, probes, max_moments,
                        keys=system.ids, progress=progress)
    finally:
        A.destroy()


def to_record(res):
    """The stored form of a KPMResult (one state of a spectrum stage's member file) with its
    D0 and omega* (NaN when unresolved)."""
    d0, wstar, raw_star, window = summary(res)
    return {"kpm_moments": res.moments, "kpm_probe_moments": res.probe_moments,
            "kpm_bounds": np.array([res.a, res.b]), "kpm_n_moments": res.n_moments,
            "kpm_negative_ritz": int(bool(res.info.get("negative_ritz", False))),
            "kpm_resolution": resolution(res.b, res.n_moments), "kpm_D0": d0,
            "kpm_omega_star": raw_star, "kpm_resolved": int(np.isfinite(wstar)),
            "kpm_seconds": res.seconds, "kpm_window": np.array(window, dtype=float),
            "omega_star_kpm_resolved": wstar}


def from_record(rec, kind):
    """The KPMResult of a stored record (to_record's inverse, up to the timing)."""
    a, b = (float(x) for x in rec["kpm_bounds"])
    return kpm.KPMResult(moments=np.asarray(rec["kpm_moments"], dtype=float),
                         probe_moments=np.asarray(rec["kpm_probe_moments"], dtype=float),
                         a=a, b=b, n_modes=int(rec["n_modes_total"]), matrix=kind,
                         probe_kind="rademacher", seed=SEED,
                         info={"negative_ritz": bool(rec["kpm_negative_ritz"])})
