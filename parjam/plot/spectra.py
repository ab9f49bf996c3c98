"""Figures of spectra: D(omega) of several matrices or ensembles (the paper's Fig. "compare"),
the transverse/longitudinal ratio eps_perp/eps_par per mode (Fig. "trans") and participation.

A whole spectrum is drawn as the histogram D(omega) of its file; the lowest k modes only
(``modes --k``) as their cumulative count N(omega), the number of modes up to omega: k modes
fill only a few bins of any width that resolves them, and a cumulative count needs none."""

import numpy as np

from parjam.plot import DPI, LEGEND_FONTSIZE, atomic_png, pyplot
from parjam.plot.labels import axis, readable_log_ticks, title
from parjam.study.summary import read_summary

WHOLE = 0.99  # a spectrum with this share of its d N' - d modes is drawn as a histogram


def _label(spec):
    a = spec.get("attrs", {})
    return f"{a.get('matrix', '?')} ({a.get('method', '?')}, {len(spec['frequency'])} modes)"


def _whole(spec):
    a = spec.get("attrs", {})
    total = int(a.get("n_modes_total", 0) or 0)
    return total > 0 and len(spec["frequency"]) >= WHOLE * total


def spectra_title(spectra):
    """N, d and the state of the packing the spectra belong to (the first one's)."""
    a = spectra[0].get("attrs", {})
    n = a.get("n") or (int(a.get("n_active", 0)) + int(a.get("n_rattlers", 0)))
    states = sorted({str(s.get("attrs", {}).get("state", "")) for s in spectra} - {""})
    if not states and a.get("pressure") is not None:  # a packing without a state label
        states = [f"p{float(a['pressure']):.1e}"]
    return title(n, a.get("dimension"), ",".join(states))


def spectra_figure(spectra, path):
    """Three panels for spectrum dicts from parjam.files.modes_io.read_spectrum."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    whole = all(_whole(s) for s in spectra)
    for spec in spectra:
        lab = _label(spec)
        w = spec["frequency"]
        dos = spec.get("dos", {})
        if whole and len(dos.get("omega", [])):
            ax[0].plot(dos["omega"], dos["density"], "-o", ms=3, label=lab)
        else:
            pos = np.sort(w[w > 0])
            ax[0].step(np.concatenate([[0.0], pos]), np.arange(len(pos) + 1), where="post",
                       label=lab)
        ratio = spec["eps_perp"] / np.maximum(spec["eps_par"], 1e-300)
        ax[1].semilogy(w, ratio, ".", ms=3, label=lab)
        ax[2].semilogy(w, spec["participation_ratio"], ".", ms=3, label=lab)
    if whole:
        ax[0].set(xlabel=axis(r"$\omega$", "frequency"),
                  ylabel=axis(r"$D(\omega)$ per mode", "dos"), title="density of states")
    else:
        window = any(np.all(np.isfinite(np.asarray(s.get("attrs", {}).get(
            "interval_lambda", [np.nan]), float))) for s in spectra)
        ax[0].set(xlabel=axis(r"$\omega$", "frequency"),
                  ylabel=r"$N(\omega)$: modes up to $\omega$",
                  title="cumulative count of the modes in the window" if window else
                  "cumulative count of the lowest modes")
        ax[0].set_xlim(left=0)
        ax[0].set_ylim(bottom=0)
    ax[1].set(xlabel=axis(r"$\omega$", "frequency"),
              ylabel=r"$\epsilon_\perp / \epsilon_\parallel$", title="transverse / longitudinal")
    ax[2].set(xlabel=axis(r"$\omega$", "frequency"), ylabel="participation ratio",
              title="participation")
    for a in ax:
        a.legend(fontsize=LEGEND_FONTSIZE)
    fig.suptitle(spectra_title(spectra), fontsize=10)
    readable_log_ticks(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def ensemble_dos_figure(omega, density, error, path, label="ensemble", omega_star=None,
                        heading=None):
    """Ensemble-averaged D(omega) with error bars (parjam dos --plot); ``heading`` names the
    ensemble (labels.title)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.8))
    ax.errorbar(omega, density, yerr=error, fmt="-o", ms=3, capsize=2,
                label=f"{label}: mean, standard error")
    if omega_star is not None and np.isfinite(omega_star):
        ax.axvline(omega_star, color="k", ls="--", lw=0.8,
                   label=rf"$\omega^*$ = {omega_star:.3g}")
    ax.set(xlabel=axis(r"$\omega$", "frequency"), ylabel=axis(r"$D(\omega)$ per mode", "dos"))
    if heading:
        ax.set_title(heading, fontsize=10)
    ax.legend(fontsize=LEGEND_FONTSIZE)
    readable_log_ticks(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def dos_pictures(path, stem, dpi):
    """D(omega) of every matrix, the states overlaid (log-linear, as the paper's figures), from
    a scene's summary file (parjam.study.summary) to STEM-dos-MATRIX.png."""
    s = read_summary(path)
    a = s["attrs"]
    states = [x.decode() for x in a["states"]]
    kinds = sorted({k for lab in states if lab in s for k in s[lab].get("spectrum", {})})
    plt = pyplot()
    for kind in kinds:
        fig, ax = plt.subplots(figsize=(5, 3.6))
        for lab in states:
            dos = s.get(lab, {}).get("spectrum", {}).get(kind, {}).get("dos")
            if dos is not None:
                ax.errorbar(dos["omega"], dos["density"], yerr=dos["density_error"], fmt="-",
                            lw=1, label=lab)
        ax.set(xlabel=axis(r"$\omega$", "frequency"),
               ylabel=axis(r"$D(\omega)$ per mode", "dos"),
               title=title(a.get("n"), a.get("d"), None, a.get("members"),
                           f"{a['system']}, {kind}"))
        ax.title.set_fontsize(9)
        ax.legend(fontsize=LEGEND_FONTSIZE)
        readable_log_ticks(fig)
        fig.tight_layout()
        with atomic_png(f"{stem}-dos-{kind}.png") as tmp:  # no partial PNG, a full disk one line
            fig.savefig(tmp, dpi=dpi)
        plt.close(fig)
