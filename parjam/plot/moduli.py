"""Figures of the moduli and lengths: moduli against dphi with fitted slopes, the structure
factors F_T and F_L of the eigenmodes with the sound lines, and the lengths l*, l_L, l_T
against dz.

    python -m parjam.plot.moduli scaling bench-out/scaling_d3_n256.json [more.json] --out m.png
    python -m parjam.plot.moduli structure lengths.h5 --out sf.png      # from parjam lengths
    python -m parjam.plot.moduli lengths a.json [b.json] --out l.png    # scripts/moduli_scaling
"""

import argparse
import json

import h5py
import numpy as np

from parjam.plot import DPI, LEGEND_FONTSIZE, pyplot
from parjam.plot.labels import axis, describe, readable_log_ticks, title
from parjam.vib.structure import StructureFactor


def _label(fits):
    return f"alpha = {fits['alpha']:g}"


def scaling_figure(results, path):
    """B, G (member means, error bars; open symbols: only members with G_min > 0) and G/B
    against dphi, each with its fitted power law; results are scripts/moduli_scaling JSONs."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for k, res in enumerate(results):
        f, rows = res["fits"], res["rows"]
        x = np.array(f["dphi"])
        tag = f"{rows[0]['d']}D, alpha = {f['alpha']:g}"
        col = f"C{k}"
        for j, key in enumerate(("B", "G")):
            m, e = np.array(f["all"][key + "_mean"]), np.array(f["all"][key + "_sem"])
            ax[j].errorbar(x, m, yerr=e, fmt="o", color=col, ms=4, capsize=2, label=tag)
            ms = np.array(f["stable"][key + "_mean"])
            ax[j].plot(x, ms, "s", mfc="none", color=col, ms=7)
            s, err = f["all"][key]
            sel = x >= (f["G_fit_from"] if key == "G" else x.min())
            _fit_line(ax[j], x[sel], m[sel], s, col, f"slope {s:.2f} ± {err:.2f} "
                      f"(expected {f['expected'][key]:g})")
        r = np.array(f["all"]["G_mean"]) / np.array(f["all"]["B_mean"])
        ax[2].plot(x, r, "o", color=col, ms=4, label=tag)
        s, err = f["all"]["G/B"]
        sel = x >= f["G_fit_from"]
        _fit_line(ax[2], x[sel], r[sel], s, col, f"slope {s:.2f} ± {err:.2f} (expected 0.5)")
    rows0 = results[0]["rows"][0] if results and results[0]["rows"] else {}
    dims = sorted({r["rows"][0]["d"] for r in results if r["rows"]})
    d = dims[0] if len(dims) == 1 else "d"
    for a, name, unit in zip(ax, ("bulk modulus B", "shear modulus G", "G / B"),
                             ("modulus", "modulus", None)):
        a.set_xscale("log")
        a.set_yscale("log")
        a.set(xlabel=r"$\Delta\phi$", title=name,
              ylabel=axis(name.split()[-1], unit, d) if unit else name)
        a.legend(fontsize=LEGEND_FONTSIZE)
    fig.suptitle(title(rows0.get("n") or rows0.get("N"), d if d != "d" else None,
                       what="moduli against the distance to jamming"), fontsize=10)
    readable_log_ticks(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def _fit_line(ax, x, y, slope, color, label):
    ok = np.isfinite(y) & (y > 0)
    if ok.sum() < 2 or not np.isfinite(slope):
        return
    a = np.mean(np.log(y[ok]) - slope * np.log(x[ok]))
    xx = np.geomspace(x[ok].min(), x[ok].max(), 20)
    ax.plot(xx, np.exp(a) * xx**slope, "-", color=color, lw=1, label=label)


def structure_figure(path_h5, path, omega_max=None, bins=60):
    """F_T(k, omega) and F_L(k, omega) maps (log colour) with the peaks, the lines c k from the
    moduli and omega*, from the file of ``parjam lengths --what speeds structure``."""
    plt = pyplot()
    with h5py.File(path_h5, "r") as f:
        g, a = f["lengths/structure"], dict(f["lengths"].attrs)
        omega, k = g["omega"][()], g["k"][()]
        W = {"T": g["weight_T"][()], "L": g["weight_L"][()]}
        peaks = {"T": g["peak_T"][()], "L": g["peak_L"][()]}

    about = describe(path_h5)
    sf = StructureFactor(omega, k, None, None, W["L"], W["T"], float(a["L"]))
    wmax = omega_max or 1.5 * np.nanmax(peaks["L"])
    edges = np.linspace(0, wmax, bins + 1)
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    kk = np.linspace(0, k.max(), 50)
    for j, part in enumerate(("T", "L")):
        F = sf.binned(edges, part)
        img = np.log10(np.maximum(F.T, 1e-4))
        ax[j].pcolormesh(np.append(k - 0.5 * np.diff(k, prepend=0), k[-1]), edges, img,
                         shading="flat", cmap="viridis", vmin=-3)
        ax[j].plot(k, peaks[part], "o", ms=4, mfc="white", mec="black", mew=0.7, ls="none",
                   label="peak")
        c = a.get(f"c_{part}")
        if c is not None:
            ax[j].plot(kk, c * kk, "r--", lw=1, label=f"$c_{part} k$ (moduli)")
        cf = a.get(f"c_{part}_fit")
        if cf is not None:
            ax[j].plot(kk, cf * kk, ":", color="magenta", lw=1.5, label="fit, smallest k")
        if "omega_star" in a:
            ax[j].axhline(a["omega_star"], color="orange", lw=1, label=r"$\omega^*$")
        ax[j].set(xlabel=axis("k", "wavenumber"), ylabel=axis(r"$\omega$", "frequency"),
                  ylim=(0, wmax), title=rf"$\log_{{10}} F_{part}(k, \omega)$")
        ax[j].legend(fontsize=LEGEND_FONTSIZE, loc="upper left")
    fig.suptitle(title(about.get("n"), about.get("d"), about.get("state"),
                       what="structure factors of the eigenmodes"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def lengths_figure(results, path):
    """l* (count and extended soft modes), its Maxwell estimate, l_L and l_T against dz
    (log-log) with the slopes -1, -1/2."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    marks = {"lstar": ("o", "l* (cut-plane count)"),
             "lstar_extended": ("s", "l* (extended soft modes)"),
             "lstar_estimate": ("x", "d z <|r_a|> / dz"),
             "l_L": ("^", "l_L = c_L / omega*"), "l_T": ("v", "l_T = c_T / omega*")}
    for k, res in enumerate(results):
        rows = res["rows"]
        d = rows[0]["d"]
        dz = np.array([r["dz"] for r in rows])
        for j, (key, (m, lab)) in enumerate(marks.items()):
            y = np.array([r.get(key, np.nan) or np.nan for r in rows], dtype=float)
            ok = np.isfinite(y) & (y > 0) & (dz > 0)
            if ok.any():
                ax.plot(dz[ok], y[ok], m, color=f"C{j}", mfc="none" if d == 2 else None,
                        label=f"{lab}, {d}D")
    x = np.geomspace(0.1, 3, 10)
    ax.plot(x, 3 / x, "k-", lw=0.7, label="slope -1")
    ax.plot(x, 0.8 / np.sqrt(x), "k--", lw=0.7, label="slope -1/2")
    ax.set(xscale="log", yscale="log", xlabel=r"dz $= z - 2d$", ylabel=axis("length", "length"))
    ns = sorted({r.get("N") or r.get("n") for res in results for r in res["rows"]} - {None})
    ax.set_title(title(ns[0] if len(ns) == 1 else None, what="lengths against dz"),
                 fontsize=10)
    readable_log_ticks(fig)
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles))  # one entry per quantity and dimension
    ax.legend(unique.values(), unique.keys(), fontsize=LEGEND_FONTSIZE, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def moduli_files_figure(paths_h5, path):
    """From files of ``parjam moduli`` (e.g. the states of a compression ladder): B, G and the
    softest shear G_min against the pressure, and G / B, log-log with fitted slopes (expected
    in 3D harmonic packings: B ~ p^0, G ~ p^(1/2))."""
    rows = []
    for p in paths_h5:
        with h5py.File(p, "r") as f:
            a = f["moduli"].attrs
            rows.append([float(a[k]) for k in ("pressure", "B", "G", "G_min")])
    about = [describe(p) for p in paths_h5]
    d = about[0].get("d") or "d"
    ns = sorted({x.get("n") for x in about} - {None})
    p, B, G, Gmin = np.array(sorted(rows)).T
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9.5, 3.8))
    for k, (y, lab, m) in enumerate(((B, "B", "o"), (G, "G", "s"), (Gmin, "G_min", "v"))):
        ok = y > 0
        ax[0].plot(p[ok], y[ok], m, color=f"C{k}", label=lab)
        if ok.sum() >= 2 and lab != "G_min":
            s = np.polyfit(np.log(p[ok]), np.log(y[ok]), 1)[0]
            _fit_line(ax[0], p[ok], y[ok], s, f"C{k}", f"{lab}: slope {s:.2f}")
    r = G / B
    ok = r > 0
    ax[1].plot(p[ok], r[ok], "o", color="C3")
    if ok.sum() >= 2:
        s = np.polyfit(np.log(p[ok]), np.log(r[ok]), 1)[0]
        _fit_line(ax[1], p[ok], r[ok], s, "C3", f"slope {s:.2f}")
    if np.any(Gmin <= 0):
        ax[0].set_title(f"{int(np.sum(Gmin <= 0))} state(s) unstable to some shear (G_min <= 0)",
                        fontsize=8)
    for a, name in zip(ax, (axis("modulus", "modulus", d), "G / B")):
        a.set(xscale="log", yscale="log", xlabel=axis("pressure $p$", "pressure", d),
              ylabel=name)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=LEGEND_FONTSIZE)
    fig.suptitle(title(ns[0] if len(ns) == 1 else None, d if d != "d" else None,
                       f"{len(rows)} states", what="moduli by linear response"), fontsize=10)
    readable_log_ticks(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description="figures of moduli, structure factors, lengths")
    ap.add_argument("kind", choices=("scaling", "structure", "lengths"))
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--omega-max", type=float)
    args = ap.parse_args(argv)
    if args.kind == "structure":
        structure_figure(args.inputs[0], args.out, args.omega_max)
        return
    results = []
    for p in args.inputs:
        with open(p) as fh:
            results.append(json.load(fh))
    (scaling_figure if args.kind == "scaling" else lengths_figure)(results, args.out)


if __name__ == "__main__":
    main()
