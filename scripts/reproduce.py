#!/usr/bin/env python3
"""The paper's figures and laws from the bundled scenes' results (docs/reproduction.md).

    mpirun -n 2 parjam run scenes/paper-3d.toml --out results/repro/paper-3d   (and the others)
    python scripts/reproduce.py --results results/repro --img docs/img \
        --json results/repro/fits.json

Reads the summary files written by ``parjam run`` (parjam.commands.run.write_summary), fits the
scaling laws with bootstrap errors over ensemble members, draws docs/img/repro_*.png and prints
the numbers (also written as JSON).  Whatever scene has not been run is skipped.
"""

import argparse
import glob
import json
import os

import numpy as np

from parjam.commands.run import read_summary
from parjam.plot import pyplot

N_BOOT = 2000


def load(results, scene):
    """{system name: summary dict} of one scene's output directory."""
    out = {}
    for path in sorted(glob.glob(os.path.join(results, scene, "summary-*.h5"))):
        s = read_summary(path)
        out[s["attrs"]["system"]] = s
    return out


def states(s, prefix="dphi"):
    labs = [x.decode() for x in s["attrs"]["states"]]
    return [lab for lab in labs if lab.startswith(prefix) and lab != "phi_c"]


def value(lab):
    return float(lab.replace("dphi", "").replace("p", ""))


def table(s, labs, kind, q, matrix=None):
    """(members, states) array of one quantity."""
    cols = []
    for lab in labs:
        g = s[lab][kind] if matrix is None else s[lab]["spectrum"][matrix]
        cols.append(np.asarray(g[q], dtype=float))
    return np.array(cols).T


# --------------------------------------------------------------------------- fits

def fit_power(X, Y, n_boot=N_BOOT, seed=0):
    """log-log least squares of mean(Y) against mean(X) over members (rows), both resampled
    together: exponent, its bootstrap error, prefactor and its error."""
    X, Y = np.asarray(X, float), np.asarray(Y, float)

    def one(rows):
        x, y = np.nanmean(X[rows], axis=0), np.nanmean(Y[rows], axis=0)
        ok = (x > 0) & (y > 0)
        if ok.sum() < 2:
            return np.nan, np.nan
        b, a = np.polyfit(np.log(x[ok]), np.log(y[ok]), 1)
        return b, np.exp(a)

    rng = np.random.default_rng(seed)
    boots = np.array([one(rng.integers(0, len(X), len(X))) for _ in range(n_boot)])
    b, a = one(np.arange(len(X)))
    return {"exponent": float(b), "exponent_err": float(np.nanstd(boots[:, 0])),
            "prefactor": float(a), "prefactor_err": float(np.nanstd(boots[:, 1])),
            "members": int(len(X)), "points": int(X.shape[1])}


def fit_eq33(W2, WS2, DZ, P, n_boot=N_BOOT, seed=0):
    """Eq. (33), omega_AM^2 = A1 dz^2 - A2 p.  Along a compression dz^2 and p are proportional
    (Eq. 22), so a joint fit cannot separate A1 from A2; instead A1 comes from the relaxed
    system, omega*_relaxed^2 = A1 dz^2 (no pressure term), and A2 per state from
    (A1 dz^2 - omega_AM^2) / p; bootstrap errors over members."""
    def one(rows):
        w2, ws2, dz, p = (np.nanmean(a[rows], axis=0) for a in (W2, WS2, DZ, P))
        a1 = np.sum(ws2 * dz**2) / np.sum(dz**4)
        a2 = (a1 * dz**2 - w2) / p
        return np.concatenate([[a1, np.mean(a2)], a2])

    rng = np.random.default_rng(seed)
    boots = np.array([one(rng.integers(0, len(W2), len(W2))) for _ in range(n_boot)])
    best = one(np.arange(len(W2)))
    err = np.nanstd(boots, axis=0)
    return {"A1": float(best[0]), "A1_err": float(err[0]), "A2": float(best[1]),
            "A2_err": float(err[1]), "A2_per_state": [float(x) for x in best[2:]],
            "A2_per_state_err": [float(x) for x in err[2:]]}


def law(fit):
    return f"{fit['exponent']:.3f} +- {fit['exponent_err']:.3f}"


# --------------------------------------------------------------------------- figures

def save(fig, img, name):
    path = os.path.join(img, f"repro_{name}.png")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    return path


def fig1(plt, systems, img):
    """Fig. 1: D(omega) of the full matrix for dphi = 1e-1 .. 1e-8."""
    fig, axes = plt.subplots(1, len(systems), figsize=(4.6 * len(systems), 3.4), squeeze=False)
    for ax, (name, s) in zip(axes[0], systems.items()):
        for lab in ["dphi1.0e-01", "dphi1.0e-02", "dphi1.0e-03", "dphi1.0e-04", "dphi1.0e-08"]:
            dos = s.get(lab, {}).get("spectrum", {}).get("full", {}).get("dos")
            if dos is not None:
                ax.plot(dos["omega"], dos["density"], "-", lw=1.2,
                        label=rf"$\delta\phi$ = {value(lab):.0e}")
        ax.set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$", title=f"{name}, full matrix")
        ax.legend(fontsize=7)
    return save(fig, img, "fig1")


def pooled_dos(s, lab, matrix, edges):
    g = s[lab]["spectrum"][matrix]
    w = g["frequency"][g["frequency"] > 0]
    n_modes = np.sum(s["attrs"]["d"] * s[lab]["network"]["N_active"] - s["attrs"]["d"])
    counts, _ = np.histogram(w, edges)
    return counts / (n_modes * np.diff(edges))


def compare(plt, systems, img):
    """Fig. "compare": full and relaxed D(omega), log-linear, at three dphi."""
    fig, axes = plt.subplots(1, len(systems), figsize=(4.6 * len(systems), 3.4), squeeze=False)
    for ax, (name, s) in zip(axes[0], systems.items()):
        for k, lab in enumerate(["dphi1.0e-01", "dphi1.0e-02", "dphi1.0e-03"]):
            if lab not in s or "relaxed" not in s[lab].get("spectrum", {}):
                continue
            top = np.percentile(s[lab]["spectrum"]["full"]["frequency"], 99)
            edges = np.linspace(0, top, 50)
            c = 0.5 * (edges[1:] + edges[:-1])
            for matrix, ls in (("full", "-"), ("relaxed", "--")):
                d = pooled_dos(s, lab, matrix, edges)
                ax.semilogy(c[d > 0], d[d > 0], ls, color=f"C{k}", lw=1.1,
                            label=f"{matrix} {value(lab):.0e}")
        ax.set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$", title=f"{name}: full (-) vs relaxed (--)")
        ax.legend(fontsize=6, ncol=2)
    return save(fig, img, "compare")


def sans(plt, systems, img, fits):
    """Fig. "sans": omega* of the relaxed system against dz."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    for k, (name, s) in enumerate(systems.items()):
        labs = [lab for lab in states(s) if value(lab) >= 1e-4]
        dz = table(s, labs, "network", "dz_iso")
        ws = table(s, labs, "spectrum", "omega_star", "relaxed")
        f = fit_power(dz, ws)
        fits[f"sans/{name}"] = f
        ax.loglog(dz.ravel(), ws.ravel(), "o", ms=3, color=f"C{k}", alpha=0.5)
        x = np.geomspace(np.nanmin(dz[dz > 0]), np.nanmax(dz), 20)
        ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                  label=f"{name}: slope {law(f)}")
    ax.set(xlabel=r"$\delta z$", ylabel=r"$\omega^*$ (relaxed)", title=r"$\omega^* \sim \delta z$")
    ax.legend(fontsize=7)
    return save(fig, img, "sans")


def trans(plt, systems, img, fits):
    """Fig. "trans": transverse and longitudinal sums per mode at dphi = 1e-8."""
    fig, axes = plt.subplots(1, len(systems), figsize=(4.6 * len(systems), 3.4), squeeze=False)
    for ax, (name, s) in zip(axes[0], systems.items()):
        g = s.get("dphi1.0e-08", {}).get("spectrum", {}).get("full", {})
        if "eps_perp" not in g:
            continue
        w, perp, par = g["frequency"], g["eps_perp"], g["eps_par"]
        ok = w > 0
        w, perp, par = w[ok], perp[ok], par[ok]
        ax.loglog(w, perp, ".", ms=1.5, color="C0", label=r"$\epsilon_\perp$ (transverse)")
        ax.loglog(w, par, ".", ms=1.5, color="C3", label=r"$\epsilon_\parallel$ (longitudinal)")
        low = w < np.quantile(w, 0.2)
        b, a = np.polyfit(np.log(w[low]), np.log(par[low]), 1)
        bp, _ = np.polyfit(np.log(w[low]), np.log(perp[low]), 1)
        fits[f"trans/{name}"] = {"par_exponent_low20pct": float(b),
                                 "perp_exponent_low20pct": float(bp),
                                 "perp_at_lowest_5pct":
                                     float(np.mean(perp[w < np.quantile(w, 0.05)])),
                                 "omega_range": [float(w[low].min()), float(w[low].max())]}
        x = np.geomspace(w.min(), w.max(), 20)
        ax.loglog(x, np.exp(a) * x**2, "k--", lw=0.8, label=r"$\propto\omega^2$")
        ax.set(xlabel=r"$\omega$", ylabel="sum per mode", title=rf"{name}, $\delta\phi=10^{{-8}}$")
        ax.legend(fontsize=7)
    return save(fig, img, "trans")


def diag(plt, systems, img, fits):
    """Fig. "diag" / Eq. (22): dz against p, dz = C0 p^(1/2); Eq. (33) gives the stability line."""
    fig, ax = plt.subplots(figsize=(4.8, 3.7))
    for k, (name, s) in enumerate(systems.items()):
        labs = [lab for lab in states(s) if value(lab) >= 1e-5]
        p = table(s, labs, "network", "pressure")
        dz = table(s, labs, "network", "dz_iso")
        f = fit_power(p, dz)
        fits[f"diag/{name}"] = f
        ax.loglog(p.ravel(), dz.ravel(), "o", ms=3, color=f"C{k}", alpha=0.5)
        x = np.geomspace(p.min(), p.max(), 20)
        ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                  label=f"{name}: slope {law(f)}, C0 = {f['prefactor']:.2f}")
        e33 = fits.get(f"eq33/{name}")
        if e33 and e33["A1"] > 0 and e33["A2"] > 0:
            line = np.sqrt(e33["A2"] / e33["A1"] * x)
            ax.fill_between(x, 1e-6, line, color=f"C{k}", alpha=0.12)
            ax.loglog(x, line, ":", color=f"C{k}", lw=1,
                      label=rf"{name}: unstable below $\sqrt{{A_2 p/A_1}}$")
    ax.set(xlabel="p", ylabel=r"$\delta z$", title=r"$\delta z = C_0\, p^{1/2}$ (Eq. 22)")
    ax.set_ylim(bottom=max(ax.get_ylim()[0], 1e-3))
    ax.legend(fontsize=6)
    return save(fig, img, "diag")


def eq33(plt, systems, img, fits):
    """Eq. (33): omega_AM^2 = A1 dz^2 - A2 p, omega_AM the onset of the full system's D(omega)
    (its omega*)."""
    fig, ax = plt.subplots(figsize=(4.6, 3.6))
    for k, (name, s) in enumerate(systems.items()):
        labs = [lab for lab in states(s) if value(lab) >= 1e-4]
        w2 = table(s, labs, "spectrum", "omega_star", "full") ** 2
        ws2 = table(s, labs, "spectrum", "omega_star", "relaxed") ** 2
        dz = table(s, labs, "network", "dz_iso")
        p = table(s, labs, "network", "pressure")
        f = fit_eq33(w2, ws2, dz, p)
        fits[f"eq33/{name}"] = f
        fits[f"eq33_relaxed_ratio/{name}"] = {
            "omega_AM2_over_omega_star2": [float(x) for x in np.nanmean(w2 / ws2, axis=0)],
            "states": labs}
        pred = f["A1"] * dz**2 - f["A2"] * p
        ax.loglog(pred.ravel(), w2.ravel(), "o", ms=3, color=f"C{k}",
                  label=f"{name}: A1 = {f['A1']:.3g}, A2 = {f['A2']:.3g}")
    lim = ax.get_xlim()
    ax.loglog(lim, lim, "k--", lw=0.8)
    ax.set(xlabel=r"$A_1\delta z^2 - A_2 p$", ylabel=r"$\omega_{AM}^2$",
           title="Eq. (33), full system")
    ax.legend(fontsize=7)
    return save(fig, img, "eq33")


def hertz(plt, systems, img, fits):
    """Hertzian contacts: dz ~ p^(1/3), omega* ~ p^(1/2), D0 ~ p^(-1/6)."""
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for k, (name, s) in enumerate(sorted(systems.items(), key=lambda t: t[1]["attrs"]["n"])):
        labs = states(s, "p")
        p = table(s, labs, "network", "pressure")
        for ax, (key, y, theory) in zip(axes, (
                ("dz", table(s, labs, "network", "dz_iso"), 1 / 3),
                ("omega_star", table(s, labs, "spectrum", "omega_star", "relaxed"), 1 / 2),
                ("D0", table(s, labs, "spectrum", "D0", "full"), -1 / 6))):
            f = fit_power(p, y)
            fits[f"hertz/{key}/{name}"] = f
            ax.loglog(p.ravel(), y.ravel(), "o", ms=3, alpha=0.6, color=f"C{k}")
            x = np.geomspace(p.min(), p.max(), 20)
            ax.loglog(x, f["prefactor"] * x ** f["exponent"], "-", color=f"C{k}",
                      label=f"N = {s['attrs']['n']}: {law(f)} (theory {theory:.3g})")
            ax.set(xlabel="p", ylabel=key, title=f"Hertz, alpha = 5/2: {key}")
            ax.legend(fontsize=7)
    return save(fig, img, "hertz")


def softmodes(plt, systems, img, fits):
    """f(x) over sizes and its lower bound c; trial-mode energies against omega_L^2."""
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.5))
    Ls, emax, emean, wl2 = [], [], [], []
    for k, (name, s) in enumerate(sorted(systems.items(), key=lambda t: t[1]["attrs"]["n"])):
        g = s["phi_c"]["softmodes"]
        ov = g["overlap"]  # members x bins x 3
        x, f = ov[0, :, 0], ov[:, :, 1].mean(axis=0)
        axes[0].plot(x, f, "-o", ms=3, label=f"N = {s['attrs']['n']}")
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
    axes[0].set(xlabel="x / L", ylabel="f(x)", title="overlap function, cut cube")
    axes[0].legend(fontsize=7)
    Ls = np.array(Ls)
    axes[1].loglog(Ls, emean, "o-", label=r"mean $\langle\delta R^*|M|\delta R^*\rangle$ (e > 0.1)")
    axes[1].loglog(Ls, emax, "s-", label="max trial energy")
    axes[1].loglog(Ls, wl2, "k--", label=r"$\omega_L^2$ (Eq. kkk)")
    if len(Ls) > 1:
        ordered = sorted(systems.values(), key=lambda s: s["attrs"]["n"])
        m = min(len(s["phi_c"]["softmodes"]["L"]) for s in ordered)
        X = np.array([s["phi_c"]["softmodes"]["L"][:m] for s in ordered]).T
        Y = np.array([s["phi_c"]["softmodes"]["omega_t2"][:m] for s in ordered]).T
        fits["softmodes/trial_energy_vs_L"] = {**fit_power(X, Y), "theory": -2.0}
    axes[1].set(xlabel="L", ylabel="energy", title="trial modes vs $\\omega_L^2$")
    axes[1].legend(fontsize=7)
    return save(fig, img, "softmodes")


def fluctuations(plt, systems, img, fits):
    """Variance of the contact number in sub-boxes of side l, against l^d (Gaussian: std
    ~ l^(d/2)) and l^(2(d-1)) (surface: std ~ l^(d-1))."""
    fig, axes = plt.subplots(1, len(systems), figsize=(4.6 * len(systems), 3.4), squeeze=False)
    for ax, (name, s) in zip(axes[0], systems.items()):
        d = int(s["attrs"]["d"])
        for k, lab in enumerate(["phi_c", "dphi1.0e-04", "dphi1.0e-02"]):
            g = s.get(lab, {}).get("fluctuations")
            if g is None:
                continue
            l = g["l"][0][1:]  # m >= 2: sub-boxes (m = 1 is the whole box, variance 0)
            std_c = np.sqrt(g["var_contacts"][:, 1:].mean(axis=0))
            std_x = np.sqrt(g["var_excess"][:, 1:].mean(axis=0))
            ax.loglog(l, std_c, "o-", color=f"C{k}", ms=3, label=f"{lab}: contacts")
            ax.loglog(l, std_x, "s--", color=f"C{k}", ms=3, label=f"{lab}: excess")
            if len(l) > 1:
                fits[f"fluct/{name}/{lab}"] = {
                    "std_contacts_exponent": float(np.polyfit(np.log(l), np.log(std_c), 1)[0]),
                    "std_excess_exponent": float(np.polyfit(np.log(l), np.log(std_x), 1)[0]),
                    "gaussian": d / 2, "surface": d - 1}
        ref = np.array([l.min(), l.max()])
        ax.loglog(ref, std_c[0] * (ref / ref[0]) ** (d / 2), "k:", label=f"l^{d / 2:g}")
        ax.loglog(ref, std_c[0] * (ref / ref[0]) ** (d - 1), "k-.", label=f"l^{d - 1}")
        ax.set(xlabel="l", ylabel="std in a sub-box", title=name)
        ax.legend(fontsize=6)
    return save(fig, img, "fluct")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default="results/repro")
    ap.add_argument("--img", default="docs/img")
    ap.add_argument("--json", default="results/repro/fits.json")
    args = ap.parse_args(argv)
    plt = pyplot()
    os.makedirs(args.img, exist_ok=True)
    fits = {}
    paper = {**load(args.results, "paper-3d"), **load(args.results, "paper-2d")}
    made = []
    if paper:
        made += [fig1(plt, paper, args.img), compare(plt, paper, args.img)]
        made.append(sans(plt, paper, args.img, fits))
        made.append(trans(plt, paper, args.img, fits))
        made.append(eq33(plt, paper, args.img, fits))
        made.append(diag(plt, paper, args.img, fits))
        made.append(fluctuations(plt, paper, args.img, fits))
    hz = load(args.results, "hertz-3d")
    if hz:
        made.append(hertz(plt, hz, args.img, fits))
    sm = load(args.results, "softmodes-3d")
    if sm:
        made.append(softmodes(plt, sm, args.img, fits))
    for name, s in {**paper, **hz, **sm}.items():
        fits[f"size/{name}"] = {"N": int(s["attrs"]["n"]), "members": int(s["attrs"]["members"])}
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(fits, fh, indent=1)
    print(json.dumps(fits, indent=1))
    print("figures:", *made, sep="\n  ")


if __name__ == "__main__":
    main()
