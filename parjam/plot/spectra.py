"""Figures of spectra: D(omega) of several matrices or ensembles (the paper's Fig. "compare"),
the transverse/longitudinal ratio eps_perp/eps_par per mode (Fig. "trans") and participation."""

import numpy as np

from parjam.plot import DPI, atomic_png, pyplot
from parjam.study.summary import read_summary


def _label(spec):
    a = spec.get("attrs", {})
    return f"{a.get('matrix', '?')} ({a.get('method', '?')})"


def spectra_figure(spectra, path):
    """Three panels for spectrum dicts from parjam.files.modes_io.read_spectrum."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    for spec in spectra:
        lab = _label(spec)
        dos = spec.get("dos", {})
        if len(dos.get("omega", [])):
            ax[0].plot(dos["omega"], dos["density"], "-o", ms=3, label=lab)
        w = spec["frequency"]
        ratio = spec["eps_perp"] / np.maximum(spec["eps_par"], 1e-300)
        ax[1].semilogy(w, ratio, ".", ms=3, label=lab)
        ax[2].semilogy(w, spec["participation_ratio"], ".", ms=3, label=lab)
    ax[0].set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$ per mode", title="density of states")
    ax[1].set(xlabel=r"$\omega$", ylabel=r"$\epsilon_\perp / \epsilon_\parallel$",
              title="transverse / longitudinal")
    ax[2].set(xlabel=r"$\omega$", ylabel="participation ratio", title="participation")
    for a in ax:
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def ensemble_dos_figure(omega, density, error, path, label="ensemble", omega_star=None):
    """Ensemble-averaged D(omega) with error bars (parjam dos --plot)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.8))
    ax.errorbar(omega, density, yerr=error, fmt="-o", ms=3, capsize=2, label=label)
    if omega_star is not None and np.isfinite(omega_star):
        ax.axvline(omega_star, color="k", ls="--", lw=0.8, label=r"$\omega^*$")
    ax.set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$ per mode")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)


def dos_pictures(path, stem, dpi):
    """D(omega) of every matrix, the states overlaid (log-linear, as the paper's figures), from
    a scene's summary file (parjam.study.summary) to STEM-dos-MATRIX.png."""
    s = read_summary(path)
    states = [x.decode() for x in s["attrs"]["states"]]
    kinds = sorted({k for lab in states if lab in s for k in s[lab].get("spectrum", {})})
    plt = pyplot()
    for kind in kinds:
        fig, ax = plt.subplots(figsize=(5, 3.6))
        for lab in states:
            dos = s.get(lab, {}).get("spectrum", {}).get(kind, {}).get("dos")
            if dos is not None:
                ax.errorbar(dos["omega"], dos["density"], yerr=dos["density_error"], fmt="-",
                            lw=1, label=lab)
        ax.set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$ per mode",
               title=f"{s['attrs']['system']}: {kind}")
        ax.legend(fontsize=8)
        fig.tight_layout()
        with atomic_png(f"{stem}-dos-{kind}.png") as tmp:  # no partial PNG, a full disk one line
            fig.savefig(tmp, dpi=dpi)
        plt.close(fig)
