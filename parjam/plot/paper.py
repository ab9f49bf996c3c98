"""The paper's figures and laws from the summary files of ``parjam run`` (docs/results/reproduction.md).

A results directory holds one subdirectory per bundled scene (``SCENES``: ``paper-3d``,
``paper-2d``, ``paper-3d-10x``, ``hertz-3d``, ``softmodes-3d``, each the ``--out`` of
``parjam run``), or the summary files of one ``parjam run`` directly.  Each figure of
``FIGURES`` uses the systems of its group that hold the data it needs (its ``needs``), fits
its laws (parjam.study.fits) into a ``fits`` dict and is drawn to ``repro_<name>.png``.
``parjam plot RESULTS --img DIR`` and ``scripts/reproduce.py`` call :func:`reproduce`.

Why one file of ~710 lines: every figure is a small function next to the laws it fits, and the
``FIGURES`` table that drives them reads best in one place.
"""

import glob
import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from parjam.files import inputs, outputs
from parjam.errors import ParjamError
from parjam.plot import DPI, LEGEND_FONTSIZE, atomic_png, pyplot
from parjam.plot.labels import axis, readable_log_ticks, state_text, title
from parjam.study.fits import bootstrap, fit_eq33, fit_power, law, log_slope

#: figure group -> the bundled scenes (subdirectories of a results directory) that feed it
SCENES = {"paper": ("paper-3d", "paper-2d", "paper-3d-10x", "paper-3d-10x-spectra"),
          "hertz": ("hertz-3d",),
          "softmodes": ("softmodes-3d",)}


# --------------------------------------------------------------------------- summaries

def read(path):
    """One summary file (parjam.study.summary.write_summary) as nested dicts; ParjamError if it
    is not one."""
    import h5py  # here: `parjam plot --help` lists the figures without loading h5py or scipy

    from parjam.study.summary import read_summary

    path = os.fspath(path)
    inputs.require(path)  # a FIFO named summary-*.h5 in a results directory: named, not opened
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    try:
        s = read_summary(path)
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise ParjamError(f"{path}: unreadable HDF5 file ({exc})") from None
    if not is_summary(s):
        raise ParjamError(f"{path}: not a summary file of parjam run (no system, states, d, n "
                          f"and members attributes)")
    return s


def is_summary(s):
    return all(k in s["attrs"] for k in ("system", "states", "d", "n", "members"))


def load(results, scene):
    """{system name: summary dict} of one scene's output directory (``scene`` = "": the
    summaries directly in ``results``)."""
    out = {}
    for path in sorted(glob.glob(os.path.join(glob.escape(results), scene, "summary-*.h5"))):
        s = read(path)
        out[s["attrs"]["system"]] = s
    return out


def read_results(results, summaries=()):
    """{group: {system: summary}}: the bundled scenes' subdirectories of ``results`` (may be
    None) by ``SCENES``; summaries directly in ``results`` and the files ``summaries`` may serve
    every group (each figure keeps the systems with the data it needs)."""
    groups = {g: {} for g in SCENES}
    direct = {}
    if results is not None:
        for g, scenes in SCENES.items():
            for scene in scenes:
                for name, summ in load(results, scene).items():
                    # two scenes of the same system (paper-3d-10x and its spectra) both drawn
                    groups[g][f"{name} [{scene}]" if name in groups[g] else name] = summ
        direct.update(load(results, ""))
    for path in summaries:
        s = read(path)
        direct[s["attrs"]["system"]] = s
    for g in groups:
        groups[g].update(direct)
    return groups


def states(s, prefix="dphi"):
    """The state labels of a summary starting with ``prefix`` (phi_c excluded), in the order of
    the run, those with results only."""
    labs = [x.decode() if isinstance(x, bytes) else str(x) for x in s["attrs"]["states"]]
    return [lab for lab in labs if lab.startswith(prefix) and lab != "phi_c" and lab in s]


def value(lab):
    return float(lab.replace("dphi", "").replace("p", ""))


def table(s, labs, kind, q, matrix=None):
    """(members, states) array of one quantity."""
    cols = []
    for lab in labs:
        g = s[lab][kind] if matrix is None else s[lab]["spectrum"][matrix]
        cols.append(np.asarray(g[q], dtype=float))
    return np.array(cols).T


def _get(s, *keys):
    for k in keys:
        if not isinstance(s, dict) or k not in s:
            return None
        s = s[k]
    return s


def _has(s, labs, *paths, at_least=2):
    """At least ``at_least`` states and every state in ``labs`` with every key path."""
    return len(labs) >= at_least and all(_get(s, lab, *p) is not None for lab in labs
                                         for p in paths)


# --------------------------------------------------------------------------- figures

FIG1_STATES = ["dphi1.0e-01", "dphi1.0e-02", "dphi1.0e-03", "dphi1.0e-04", "dphi1.0e-08"]
COMPARE_STATES = ["dphi1.0e-01", "dphi1.0e-02", "dphi1.0e-03"]


def who(s):
    """N, d and the members of a system (a summary's attributes), for titles and legends."""
    a = s["attrs"]
    return title(a.get("n"), a.get("d"), None, a.get("members"))


def span(labs):
    """The states a figure draws, as a range: ``dphi = 1e-05 .. 1e-01``."""
    vals = sorted(value(lab) for lab in labs)
    if not vals:
        return ""
    name = r"$\delta\phi$" if labs[0].startswith("dphi") else "p"
    return f"{name} = {vals[0]:.0e}" + (f" .. {vals[-1]:.0e}" if len(vals) > 1 else "")


def everyone(systems):
    """The second title line of a figure drawing several systems: each one's N, d, members."""
    return "; ".join(who(s) for s in systems.values())


def single(ax, heading, systems):
    """Title (the law and its states, then the systems) and legend of a one-panel figure whose
    points lie along a rising diagonal: the legend goes to the upper left."""
    ax.set_title(f"{heading}\n{everyone(systems)}", fontsize=9)
    ax.legend(fontsize=LEGEND_FONTSIZE - 1, loc="upper left")


def common_d(systems):
    """The dimension of every system drawn, or "d" when they mix."""
    dims = {int(s["attrs"]["d"]) for s in systems.values()}
    return dims.pop() if len(dims) == 1 else "d"


def _panels(plt, systems):
    fig, axes = plt.subplots(1, len(systems), figsize=(4.6 * len(systems), 3.4), squeeze=False)
    return fig, axes[0]


def fig1_states(s):
    """FIG1_STATES, and the state closest to jamming of a ladder without dphi = 1e-8 (N = 10240:
    dphi = 1e-6)."""
    labs = [lab for lab in FIG1_STATES if _get(s, lab, "spectrum", "full", "dos") is not None]
    low = [lab for lab in states(s) if _get(s, lab, "spectrum", "full", "dos") is not None]
    if low and "dphi1.0e-08" not in labs and low[0] not in labs:
        labs.append(low[0])
    return labs


def _source(doses):
    """'dense', or 'KPM, M1 - M2 moments' over the D(omega)s drawn."""
    m = [int(x) for d in doses if "kpm_moments" in d for x in d["kpm_moments"]]
    if not m:
        return "dense"
    return f"KPM, {min(m)} moments" if min(m) == max(m) else \
        f"KPM, {min(m)} - {max(m)} moments"


def fig1(plt, systems, fits):
    """Fig. 1: D(omega) of the full matrix for dphi = 1e-1 .. 1e-8 (the ladder's lowest state
    where 1e-8 is missing), ensemble mean with its error band."""
    fig, axes = _panels(plt, systems)
    for ax, (name, s) in zip(axes, systems.items()):
        labs = fig1_states(s)
        src = _source([s[lab]["spectrum"]["full"]["dos"] for lab in labs])
        for k, lab in enumerate(labs):
            dos = s[lab]["spectrum"]["full"]["dos"]
            ax.plot(dos["omega"], dos["density"], "-", lw=1.2, color=f"C{k}",
                    label=rf"$\delta\phi$ = {value(lab):.0e}")
            if "density_error" in dos:
                ax.fill_between(dos["omega"], dos["density"] - dos["density_error"],
                                dos["density"] + dos["density_error"], color=f"C{k}",
                                alpha=0.25, lw=0)
        ax.set(xlabel=axis(r"$\omega$", "frequency"), ylabel=axis(r"$D(\omega)$", "dos"),
               title=f"{name}, full matrix, {src}\n{who(s)}")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=LEGEND_FONTSIZE)
    return fig


def pooled_dos(s, lab, matrix, edges):
    g = s[lab]["spectrum"][matrix]
    w = g["frequency"][g["frequency"] > 0]
    n_modes = np.sum(s["attrs"]["d"] * s[lab]["network"]["N_active"] - s["attrs"]["d"])
    counts, _ = np.histogram(w, edges)
    return counts / (n_modes * np.diff(edges))


def _kpm_dos(s, lab, matrix):
    dos = _get(s, lab, "spectrum", matrix, "dos")
    return dos if dos is not None and "kpm_moments" in dos else None


def _compare_ok(s, lab):
    if all(_kpm_dos(s, lab, m) is not None for m in ("full", "relaxed")):
        return True
    return all(_get(s, lab, *p) is not None for p in (
        ("spectrum", "full", "frequency"), ("spectrum", "relaxed", "frequency"),
        ("network", "N_active")))


def _compare_kpm(ax, s, lab, k):
    """Full and relaxed D(omega) of one state from the KPM moments, with error bands; the
    frequencies up to 2 omega* of the relaxed system at the largest dphi drawn, densities down
    to 1e-3 (below, the kernel's tail)."""
    top = 2.0 * np.nanmean(s[COMPARE_STATES[0]]["spectrum"]["relaxed"]["omega_star"]) \
        if _kpm_dos(s, COMPARE_STATES[0], "relaxed") is not None else None
    if top and np.isfinite(top):
        ax.set_xlim(0, top)
    ax.set_ylim(1e-3, 1.0)
    for matrix, ls in (("full", "-"), ("relaxed", "--")):
        dos = _kpm_dos(s, lab, matrix)
        w, d, e = dos["omega"], dos["density"], dos["density_error"]
        ok = d > 0
        ax.semilogy(w[ok], d[ok], ls, color=f"C{k}", lw=1.1,
                    label=f"{matrix} {value(lab):.0e}")
        ax.fill_between(w[ok], np.clip(d - e, d / 10, None)[ok], (d + e)[ok], color=f"C{k}",
                        alpha=0.2, lw=0)


def compare(plt, systems, fits):
    """Fig. "compare": full and relaxed D(omega), log-linear, at three dphi."""
    fig, axes = _panels(plt, systems)
    for ax, (name, s) in zip(axes, systems.items()):
        for k, lab in enumerate(COMPARE_STATES):
            if not _compare_ok(s, lab):
                continue
            if all(_kpm_dos(s, lab, m) is not None for m in ("full", "relaxed")):
                _compare_kpm(ax, s, lab, k)
                continue
            top = np.percentile(s[lab]["spectrum"]["full"]["frequency"], 99)
            edges = np.linspace(0, top, 50)
            c = 0.5 * (edges[1:] + edges[:-1])
            for matrix, ls in (("full", "-"), ("relaxed", "--")):
                d = pooled_dos(s, lab, matrix, edges)
                ax.semilogy(c[d > 0], d[d > 0], ls, color=f"C{k}", lw=1.1,
                            label=f"{matrix} {value(lab):.0e}")
        ax.set(xlabel=axis(r"$\omega$", "frequency"), ylabel=axis(r"$D(\omega)$", "dos"),
               title=f"{name}: full (-) vs relaxed (--)\n{who(s)}")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=LEGEND_FONTSIZE, ncol=2)
    return fig


SANS_MIN_EXCESS = 10  # contacts above isostatic, member mean


def _excess(s, lab):
    x = _get(s, lab, "network", "excess")
    return np.nanmean(np.asarray(x, dtype=float)) if x is not None else 0.0


def _sans_states(s):
    """States with omega* of the relaxed system at dphi >= 1e-4, or below where a state still
    has SANS_MIN_EXCESS excess contacts: with fewer, omega* is set by the lowest modes of the
    finite box, not by dz.  At N = 1024 this is dphi >= 1e-4 (2D and 3D); at N = 10240 it adds
    dphi = 1e-5 (117 contacts)."""
    return [lab for lab in states(s) if _finite(s, lab, "relaxed")
            and (value(lab) >= 1e-4 or _excess(s, lab) >= SANS_MIN_EXCESS)]


def _finite(s, lab, matrix):
    """omega* of the matrix at the state, finite for at least one member (a KPM omega* the
    kernel does not resolve, or lowest modes that do not reach 2 omega*, are NaN)."""
    x = _get(s, lab, "spectrum", matrix, "omega_star")
    return x is not None and np.any(np.isfinite(np.asarray(x, dtype=float)))


def _eq33_states(s):
    """The states of Fig. "sans" with omega_AM (omega* of the full matrix) too."""
    return [lab for lab in _sans_states(s) if _finite(s, lab, "full")]


def sans(plt, systems, fits):
    """Fig. "sans": omega* of the relaxed system against dz_iso (the states of _sans_states)."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    for k, (name, s) in enumerate(systems.items()):
        labs = _sans_states(s)
        dz = table(s, labs, "network", "dz_iso")
        ws = table(s, labs, "spectrum", "omega_star", "relaxed")
        f = fit_power(dz, ws)
        fits[f"sans/{name}"] = f
        ax.loglog(dz.ravel(), ws.ravel(), "o", ms=3, color=f"C{k}", alpha=0.5)
        x = np.geomspace(np.nanmin(dz[dz > 0]), np.nanmax(dz), 20)
        ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                  label=f"{name}: slope {law(f)}")
    labs = sorted({lab for s in systems.values() for lab in _sans_states(s)}, key=value)
    ax.set(xlabel=r"dz_iso $= z - z_{iso}$", ylabel=axis(r"$\omega^*$ (relaxed)", "frequency"))
    single(ax, r"$\omega^* \sim$ dz_iso, " + span(labs), systems)
    return fig


def trans_state(s):
    """dphi = 1e-8 (the paper's), else the ladder's lowest state with per-mode sums of the full
    matrix (N = 10240: dphi = 1e-6, from the lowest k modes)."""
    labs = [lab for lab in ["dphi1.0e-08"] + states(s)
            if "eps_perp" in (_get(s, lab, "spectrum", "full") or {})]
    return labs[0] if labs else None


def _complete(s, lab):
    """Every non-translational mode of every member computed (a dense spectrum)?"""
    g = s[lab]["spectrum"]["full"]
    total = np.nansum(s["attrs"]["d"] * s[lab]["network"]["N_active"] - s["attrs"]["d"])
    return len(g["frequency"]) >= 0.99 * total


def trans_fit(w, perp, par, member, complete):
    """Slopes of eps_par and eps_perp against omega in log-log: over the lowest 20 % of the
    modes of a complete spectrum (the N = 1024 path), over every computed mode of a partial
    one (the lowest k: the range they cover); bootstrap errors over members."""
    def one(rows):
        sel = np.isin(member, rows)
        ww, pp, qq = w[sel], perp[sel], par[sel]
        low = ww < np.quantile(ww, 0.2) if complete else np.ones(len(ww), bool)
        return np.array([log_slope(ww[low], qq[low])[0], log_slope(ww[low], pp[low])[0]])

    ids = np.unique(member)
    best, boots = bootstrap(lambda r: one(ids[r]), len(ids))
    low = w < np.quantile(w, 0.2) if complete else np.ones(len(w), bool)
    return best, np.nanstd(boots, axis=0), low


def trans(plt, systems, fits):
    """Fig. "trans": transverse and longitudinal sums per mode at dphi = 1e-8 (trans_state),
    slopes by trans_fit."""
    fig, axes = _panels(plt, systems)
    for ax, (name, s) in zip(axes, systems.items()):
        lab = trans_state(s)
        if lab is None:
            continue
        g = s[lab]["spectrum"]["full"]
        w, perp, par, member = g["frequency"], g["eps_perp"], g["eps_par"], g["member_of_mode"]
        ok = w > 0
        w, perp, par, member = w[ok], perp[ok], par[ok], member[ok]
        complete = _complete(s, lab)
        ax.loglog(w, perp, ".", ms=1.5, color="C0", label=r"$\epsilon_\perp$ (transverse)")
        ax.loglog(w, par, ".", ms=1.5, color="C3", label=r"$\epsilon_\parallel$ (longitudinal)")
        (b, bp), (b_err, bp_err), low = trans_fit(w, perp, par, member, complete)
        a = log_slope(w[low], par[low])[1]
        rng = [float(w[low].min()), float(w[low].max())]
        if complete:  # the keys of the N = 1024 path
            fits[f"trans/{name}"] = {"par_exponent_low20pct": float(b),
                                     "perp_exponent_low20pct": float(bp),
                                     "perp_at_lowest_5pct":
                                         float(np.mean(perp[w < np.quantile(w, 0.05)])),
                                     "omega_range": rng}
        else:
            fits[f"trans/{name}"] = {"state": lab, "modes": int(len(w)),
                                     "fit_range": "every computed mode (the lowest k)",
                                     "omega_range": rng, "par_exponent": float(b),
                                     "perp_exponent": float(bp),
                                     "perp_mean": float(np.mean(perp)),
                                     "perp_std": float(np.std(perp))}
        fits[f"trans/{name}"].update(par_exponent_err=float(b_err),
                                     perp_exponent_err=float(bp_err))
        x = np.geomspace(w.min(), w.max(), 20)
        ax.loglog(x, np.exp(a) * x**2, "k--", lw=0.8, label=r"$\propto\omega^2$")
        if not complete:
            ax.axvspan(*rng, color="0.9", zorder=0)
        ax.set(xlabel=axis(r"$\omega$", "frequency"), ylabel="sum per mode",
               title=rf"{name}, $\delta\phi$ = {value(lab):.0e}, {who(s)}"
               + ("" if complete else f"\nlowest {len(w) // len(np.unique(member))} modes "
                                      f"per member"))
        ax.title.set_fontsize(9)
        ax.legend(fontsize=LEGEND_FONTSIZE)
    return fig


def _trans_ok(s):
    lab = trans_state(s)
    if lab is None:
        return False
    g = s[lab]["spectrum"]["full"]
    return all(k in g for k in ("frequency", "eps_perp", "eps_par")) and np.sum(
        np.asarray(g["frequency"]) > 0) >= 10


def eq33_fit(name, s, fits):
    """Eq. (33) fit of one system over dphi >= 1e-4 into ``fits`` (eq33/ and
    eq33_relaxed_ratio/); returns the fit and the tables it used."""
    labs = _eq33_states(s)
    w2 = table(s, labs, "spectrum", "omega_star", "full") ** 2
    ws2 = table(s, labs, "spectrum", "omega_star", "relaxed") ** 2
    dz = table(s, labs, "network", "dz_iso")
    p = table(s, labs, "network", "pressure")
    f = fit_eq33(w2, ws2, dz, p)
    fits[f"eq33/{name}"] = f
    fits[f"eq33_relaxed_ratio/{name}"] = {
        "omega_AM2_over_omega_star2": [float(x) for x in np.nanmean(w2 / ws2, axis=0)],
        "states": labs}
    return f, w2, dz, p


def _eq33_ok(s):
    return _has(s, _eq33_states(s), ("spectrum", "full", "omega_star"),
                ("spectrum", "relaxed", "omega_star"), ("network", "dz_iso"),
                ("network", "pressure"))


def eq33(plt, systems, fits):
    """Eq. (33): omega_AM^2 = A1 dz_iso^2 - A2 p, omega_AM the onset of the full system's D(omega)
    (its omega*)."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    for k, (name, s) in enumerate(systems.items()):
        f, w2, dz, p = eq33_fit(name, s, fits)
        pred = f["A1"] * dz**2 - f["A2"] * p
        ax.loglog(pred.ravel(), w2.ravel(), "o", ms=3, color=f"C{k}",
                  label=f"{name}: A1 = {f['A1']:.3g}, A2 = {f['A2']:.3g}")
    lim = ax.get_xlim()
    ax.loglog(lim, lim, "k--", lw=0.8)
    labs = sorted({lab for s in systems.values() for lab in _eq33_states(s)}, key=value)
    ax.set(xlabel=axis(r"$A_1$ dz_iso$^2 - A_2 p$", "eigenvalue"),
           ylabel=axis(r"$\omega_{AM}^2$", "eigenvalue"))
    single(ax, "Eq. (33), full system, " + span(labs), systems)
    return fig


def _diag_states(s):
    return [lab for lab in states(s) if value(lab) >= 1e-5]


def diag(plt, systems, fits):
    """Fig. "diag" / Eq. (22): dz_iso against p (dphi >= 1e-5), dz_iso = C0 p^(1/2); Eq. (33) gives the
    stability line (fitted here too when the eq33 figure is not drawn)."""
    fig, ax = plt.subplots(figsize=(4.8, 3.7))
    for k, (name, s) in enumerate(systems.items()):
        labs = _diag_states(s)
        p = table(s, labs, "network", "pressure")
        dz = table(s, labs, "network", "dz_iso")
        f = fit_power(p, dz)
        fits[f"diag/{name}"] = f
        ax.loglog(p.ravel(), dz.ravel(), "o", ms=3, color=f"C{k}", alpha=0.5)
        x = np.geomspace(p.min(), p.max(), 20)
        ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                  label=f"{name}: slope {law(f)}, C0 = {f['prefactor']:.2f}")
        e33 = fits.get(f"eq33/{name}")
        if e33 is None and _eq33_ok(s):
            e33 = eq33_fit(name, s, fits)[0]
        if e33 and e33["A1"] > 0 and e33["A2"] > 0:
            line = np.sqrt(e33["A2"] / e33["A1"] * x)
            ax.fill_between(x, 1e-6, line, color=f"C{k}", alpha=0.12)
            ax.loglog(x, line, ":", color=f"C{k}", lw=1,
                      label=r"unstable below $\sqrt{A_2 p/A_1}$")
    labs = sorted({lab for s in systems.values() for lab in _diag_states(s)}, key=value)
    ax.set(xlabel=axis("$p$", "pressure", common_d(systems)), ylabel=r"dz_iso $= z - z_{iso}$")
    ax.set_ylim(bottom=max(ax.get_ylim()[0], 1e-3))
    single(ax, r"dz_iso $= C_0\, p^{1/2}$ (Eq. 22), " + span(labs), systems)
    return fig


def _fluct_states(s):
    """The states with sub-box fluctuations: phi_c (when the bisection wrote it) and the ladder."""
    return [lab for lab in ["phi_c"] + states(s)
            if _get(s, lab, "fluctuations", "l") is not None]


def _fluct_ok(s):
    return any(np.shape(s[lab]["fluctuations"]["l"])[-1] >= 2 for lab in _fluct_states(s))


def fluct(plt, systems, fits):
    """Variance of the contact number in sub-boxes of side l = L/m, against l^d (Gaussian: std
    ~ l^(d/2)) and l^(2(d-1)) (surface: std ~ l^(d-1)): one point per sub-box size m >= 2 (the
    member mean; m = 1 is the whole box, variance 0), the x axis labelled at those sizes.  A
    small N allows one size only (l = L/m must stay above two diameters): then no slope, and
    the reference lines are left out."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    fig, axes = _panels(plt, systems)
    for ax, (name, s) in zip(axes, systems.items()):
        d = int(s["attrs"]["d"])
        by_m = {}  # sub-box index m - 2 -> its side in every state (L differs a little)
        labs = _fluct_states(s)
        for k, lab in enumerate(labs):
            g = s[lab]["fluctuations"]
            l = np.nanmean(np.atleast_2d(g["l"])[:, 1:], axis=0)
            std_c = np.sqrt(np.nanmean(np.atleast_2d(g["var_contacts"])[:, 1:], axis=0))
            std_x = np.sqrt(np.nanmean(np.atleast_2d(g["var_excess"])[:, 1:], axis=0))
            for j, side in enumerate(l):
                by_m.setdefault(j, []).append(side)
            ax.loglog(l, std_c, "o-", color=f"C{k}", ms=4, label=state_text(lab))
            ax.loglog(l, std_x, "s--", color=f"C{k}", ms=4, mfc="none")
            if len(l) > 1:
                fits[f"fluct/{name}/{lab}"] = {
                    "std_contacts_exponent": float(log_slope(l, std_c)[0]),
                    "std_excess_exponent": float(log_slope(l, std_x)[0]),
                    "gaussian": d / 2, "surface": d - 1}
        sizes = np.array([np.mean(by_m[j]) for j in sorted(by_m)])
        if len(sizes) > 1:
            ref = np.array([sizes.min(), sizes.max()])
            if d / 2 == d - 1:  # 2D: the Gaussian and the surface law coincide
                ax.loglog(ref, std_c[0] * (ref / ref[0]), "k:", label="~ l (Gaussian = surface)")
            else:
                ax.loglog(ref, std_c[0] * (ref / ref[0]) ** (d / 2), "k:",
                          label=f"~ l^{d / 2:g} (Gaussian)")
                ax.loglog(ref, std_c[0] * (ref / ref[0]) ** (d - 1), "k-.",
                          label=f"~ l^{d - 1} (surface)")
        ax.set_xlim(sizes.min() / 1.25, sizes.max() * 1.25)
        ax.xaxis.set_major_locator(FixedLocator(sizes))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.2f}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set(xlabel=axis("sub-box side l = L/m", "length"),
               ylabel="std of the count in a sub-box",
               title=f"{name}: contacts (o), excess (s)\n{who(s)}"
               + ("" if len(sizes) > 1 else ", one sub-box size at this N"))
        ax.title.set_fontsize(9)
        ax.legend(fontsize=LEGEND_FONTSIZE - 1, loc="best", framealpha=0.6)
    return fig


def _by_size(systems):
    return sorted(systems.items(), key=lambda t: t[1]["attrs"]["n"])


HERTZ_UNITS = {"dz_iso": None, "omega_star": "frequency", "D0": "dos"}


def hertz(plt, systems, fits):
    """Hertzian contacts: dz_iso ~ p^(1/3), omega* ~ p^(1/2), D0 ~ p^(-1/6)."""
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for k, (name, s) in enumerate(_by_size(systems)):
        labs = states(s, "p")
        p = table(s, labs, "network", "pressure")
        for ax, (key, y, theory) in zip(axes, (
                ("dz_iso", table(s, labs, "network", "dz_iso"), 1 / 3),
                ("omega_star", table(s, labs, "spectrum", "omega_star", "relaxed"), 1 / 2),
                ("D0", table(s, labs, "spectrum", "D0", "full"), -1 / 6))):
            f = fit_power(p, y)
            fits[f"hertz/{key}/{name}"] = f
            ax.loglog(p.ravel(), y.ravel(), "o", ms=3, alpha=0.6, color=f"C{k}")
            x = np.geomspace(p.min(), p.max(), 20)
            ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                      label=f"{who(s)}: {law(f)} (theory {theory:.3g})")
            ax.set(xlabel=axis("$p$", "pressure", s["attrs"]["d"]),
                   ylabel=axis(key, HERTZ_UNITS[key]) if HERTZ_UNITS[key] else key,
                   title=f"Hertz, alpha = 5/2: {key}, " + span(labs))
            ax.legend(fontsize=LEGEND_FONTSIZE)
    return fig


def softmodes(plt, systems, fits):
    """f(x) over sizes and its lower bound c; trial-mode energies against omega_L^2."""
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.5))
    Ls, emax, emean, wl2 = [], [], [], []
    for k, (name, s) in enumerate(_by_size(systems)):
        g = s["phi_c"]["softmodes"]
        ov = g["overlap"]  # members x bins x 3
        x, f = ov[0, :, 0], ov[:, :, 1].mean(axis=0)
        axes[0].plot(x, f, "-o", ms=3, label=f"{who(s)}, c = min f = {np.mean(g['c']):.2f}")
        c = g["c"]
        fits[f"softmodes/{name}"] = {"c_mean": float(np.mean(c)),
                                     "c_err": float(np.std(c) / np.sqrt(len(c))),
                                     "c_nontrivial": float(np.mean(g["c_nontrivial"])),
                                     "q_prime_over_q": float(np.mean(g["q_prime_over_q"])),
                                     "trial_max_over_omega_L2": float(np.nanmax(
                                         g["trial_energy_max"] / g["omega_L2"])),
                                     "excess": [int(v) for v in s["phi_c"]["network"]["excess"]]}
        Ls.append(np.mean(g["L"]))
        te = g["trial_energy"]
        emean.append(np.nanmean(te[g["extension"] > 0.1]))
        emax.append(np.nanmean(g["trial_energy_max"]))
        wl2.append(np.mean(g["omega_L2"]))
    axes[0].set(xlabel="x / L", ylabel="f(x) L", title=r"overlap function, cut cube, $\phi_c$")
    axes[0].legend(fontsize=LEGEND_FONTSIZE)
    Ls = np.array(Ls)
    axes[1].loglog(Ls, emean, "o-", label=r"mean $\langle\delta R^*|M|\delta R^*\rangle$ (e > 0.1)")
    axes[1].loglog(Ls, emax, "s-", label="max trial energy")
    axes[1].loglog(Ls, wl2, "k--", label=r"$\omega_L^2$ (Eq. kkk)")
    if len(Ls) > 1:
        ordered = [s for _, s in _by_size(systems)]
        m = min(len(s["phi_c"]["softmodes"]["L"]) for s in ordered)
        X = np.array([s["phi_c"]["softmodes"]["L"][:m] for s in ordered]).T
        Y = np.array([s["phi_c"]["softmodes"]["omega_t2"][:m] for s in ordered]).T
        fits["softmodes/trial_energy_vs_L"] = {**fit_power(X, Y), "theory": -2.0}
    axes[1].set(xlabel=axis("L", "length"), ylabel=axis("energy", "stiffness"),
                title=r"trial modes vs $\omega_L^2$, $\phi_c$")
    axes[1].legend(fontsize=LEGEND_FONTSIZE)
    return fig


_SOFT_KEYS = ("overlap", "c", "c_nontrivial", "q_prime_over_q", "trial_energy_max", "omega_L2",
              "L", "trial_energy", "extension", "omega_t2")


@dataclass(frozen=True)
class Figure:
    name: str  # drawn to repro_<name>.png
    group: str  # key of SCENES
    draw: Callable  # draw(plt, systems, fits) -> matplotlib Figure; fills fits
    needs: Callable  # needs(summary) -> bool: the system has this figure's data
    what: str  # one line for --help


#: every figure, in drawing order (eq33 before diag: diag draws the Eq. (33) stability line)
FIGURES = {f.name: f for f in (
    Figure("fig1", "paper", fig1,
           lambda s: any(_get(s, lab, "spectrum", "full", "dos") is not None
                         for lab in FIG1_STATES),
           "Fig. 1: D(omega) of the full matrix, dphi = 1e-1 .. 1e-8"),
    Figure("compare", "paper", compare,
           lambda s: any(_compare_ok(s, lab) for lab in COMPARE_STATES),
           "Fig. 'compare': full vs relaxed D(omega) at dphi = 1e-1, 1e-2, 1e-3"),
    Figure("sans", "paper", sans,
           lambda s: _has(s, _sans_states(s), ("network", "dz_iso"),
                          ("spectrum", "relaxed", "omega_star")),
           "Fig. 'sans': omega* (relaxed) against dz_iso, power-law fit"),
    Figure("trans", "paper", trans, _trans_ok,
           "Fig. 'trans': eps_perp and eps_par per mode at dphi = 1e-8"),
    Figure("eq33", "paper", eq33, _eq33_ok, "Eq. (33): omega_AM^2 = A1 dz_iso^2 - A2 p"),
    Figure("diag", "paper", diag,
           lambda s: _has(s, _diag_states(s), ("network", "dz_iso"), ("network", "pressure")),
           "Fig. 'diag' / Eq. (22): dz_iso = C0 p^(1/2)"),
    Figure("fluct", "paper", fluct, _fluct_ok,
           "contact-number fluctuations in sub-boxes against l"),
    Figure("hertz", "hertz", hertz,
           lambda s: _has(s, states(s, "p"), ("network", "dz_iso"), ("network", "pressure"),
                          ("spectrum", "relaxed", "omega_star"), ("spectrum", "full", "D0")),
           "Hertz (alpha = 5/2): dz_iso, omega*, D0 against p"),
    Figure("softmodes", "softmodes", softmodes,
           lambda s: all(_get(s, "phi_c", "softmodes", k) is not None for k in _SOFT_KEYS)
           and _get(s, "phi_c", "network", "excess") is not None,
           "soft modes of cut cubes: f(x), trial energies against omega_L^2"),
)}


def available(groups, names=None):
    """{figure name: {system: summary}} of the figures (all, or ``names``) with data."""
    out = {}
    for name in names or FIGURES:
        fig = FIGURES[name]
        systems = {n: s for n, s in groups[fig.group].items() if fig.needs(s)}
        if systems:
            out[name] = systems
    return out


def save(plt, fig, path):
    """tight layout, PNG at DPI through a temporary name (no partial file), figure closed."""
    readable_log_ticks(fig)
    with atomic_png(path) as tmp:
        fig.tight_layout()
        fig.savefig(tmp, dpi=DPI, format="png")
    plt.close(fig)
    return path


def draw(groups, img, names=None, fits=None, out=None):
    """Draw the figures ``names`` (default: every figure with data) of ``groups``
    (read_results) to ``img``/repro_<name>.png (or to ``out`` for a single figure); their fits
    go into ``fits``.  Returns (paths written, fits)."""
    fits = {} if fits is None else fits
    plt = pyplot()
    made = []
    for name, systems in available(groups, names).items():
        fig = FIGURES[name].draw(plt, systems, fits)
        made.append(save(plt, fig, out or os.path.join(img, f"repro_{name}.png")))
    return made, fits


def sizes(groups, fits):
    """size/<system>: N and members of every system read."""
    for g in groups.values():
        for name, s in g.items():
            fits[f"size/{name}"] = {"N": int(s["attrs"]["n"]),
                                    "members": int(s["attrs"]["members"])}
    return fits


def write_json(path, fits):
    """The fits as JSON (indent 1), written atomically (parjam.files.outputs); an undefined value
    (NaN, inf) is null, so that the file is valid JSON."""
    outputs.write_bytes(path, outputs.json_text(fits, indent=1).encode(), make_dirs=True)


def reproduce(results, img, json_path=None, names=None):
    """Every figure (or ``names``) with data under ``results`` drawn to ``img``, its fits and
    the sizes of the systems (written to ``json_path`` if given).  Returns (paths, fits)."""
    groups = read_results(results)
    made, fits = draw(groups, img, names)
    sizes(groups, fits)
    if json_path:
        write_json(json_path, fits)
    return made, fits
