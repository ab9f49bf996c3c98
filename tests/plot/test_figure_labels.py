"""What every figure says about itself: a title naming N, d and the state,
a reduced unit on every dimensionful axis, readable log ticks, cumulative counts for the lowest
k modes, legends that say what c and the bracketed numbers are.  Each figure is caught as it is
saved (matplotlib's Figure.savefig wrapped) and its texts read; the figures of the 2D N = 128
reference files."""

import os
import re

import numpy as np
import pytest

from conftest import DATA
from parjam import cli, env

MPI = env.petsc().COMM_WORLD.tompi4py()
REF2D = os.path.join(DATA, "ref_d2_bi_N128_dphi1e-03.h5")
REF2D_LOW = os.path.join(DATA, "ref_d2_bi_N128_dphi1e-06.h5")
SOFT2D = os.path.join(DATA, "soft_d2_N128_m0.h5")

#: axis labels that name a dimensionful quantity: each must carry its [unit]
DIMENSIONFUL = re.compile(r"omega|D\(|pressure|\$p\$|modulus|^k\b|length|side l|^L\b|energy")
#: ... unless it is a count or a ratio of them: N(omega) counts modes
DIMENSIONLESS = re.compile(r"^\$N\(")


@pytest.fixture
def saved(monkeypatch):
    """The texts of every figure saved while the test runs: [(titles, axis labels, legend
    texts, figure)]."""
    from matplotlib.figure import Figure

    seen = []
    original = Figure.savefig

    def spy(self, *args, **kw):
        axes = [a for a in self.axes if a.get_visible()]
        titles = [self._suptitle.get_text()] if self._suptitle is not None else []
        titles += [a.get_title() for a in axes]
        labels = [a.get_xlabel() for a in axes] + [a.get_ylabel() for a in axes]
        legends = [t.get_text() for a in axes if a.get_legend() for t in a.get_legend().texts]
        seen.append((titles, labels, legends, self))
        return original(self, *args, **kw)

    monkeypatch.setattr(Figure, "savefig", spy)
    return seen


def _check_units(labels):
    for label in labels:
        if DIMENSIONFUL.search(label.replace("\\", "")) and not DIMENSIONLESS.search(label):
            assert "[" in label and "]" in label, f"axis {label!r} has no unit"


def test_every_file_figure_names_its_state_and_units(shared_tmp, saved):
    d = os.path.join(shared_tmp, "labels")
    q = ["-q"]
    assert cli.main(["modes", REF2D, "--k", "20", "--out", f"{d}/spec.h5"] + q) == 0
    assert cli.main(["modes", REF2D_LOW, "--k", "20", "--out", f"{d}/spec2.h5"] + q) == 0
    assert cli.main(["dos", f"{d}/spec.h5", f"{d}/spec2.h5", "--bins", "8", "--out",
                     f"{d}/dos.h5", "--plot", f"{d}/dos.png"]) == 0
    assert cli.main(["softmodes", SOFT2D, "--cut", "x=0.5", "--out", f"{d}/soft.h5"] + q) == 0
    assert cli.main(["moduli", REF2D, "--out", f"{d}/mod1.h5"] + q) == 0
    assert cli.main(["moduli", REF2D_LOW, "--out", f"{d}/mod2.h5"] + q) == 0
    for args in ([f"{d}/spec.h5"], [f"{d}/soft.h5"], [f"{d}/mod1.h5", f"{d}/mod2.h5"],
                 [SOFT2D, "--figures", "figs"]):
        assert cli.main(["plot", *args, "--out", f"{d}/x.png", "-q"]) == 0
    if MPI.Get_rank() != 0:
        assert saved == []  # rank 0 draws
        return
    assert len(saved) == 5
    for titles, labels, legends, _ in saved:
        heading = " ".join(titles)
        assert "N = 128" in heading and "2D" in heading, heading
        _check_units(labels)
    dos, spectra, soft, moduli, figs = saved  # dos --plot first, then the four plots
    # these reference packings have no state label: their pressure names them
    assert re.search(r"p = \de-0\d", spectra[0][0]), spectra[0]
    assert "2 members" in dos[0][0] and re.search(r"p = \de-0\d", dos[0][0]), dos[0]
    # a packing of parjam pack: its label (dphi = 1e-08, the soft-mode reference)
    assert r"$\delta\phi$ = 1e-08" in figs[0][0] or "phi = " in " ".join(figs[0])
    # --k 20: the lowest modes as a cumulative count, not a histogram of ~4 bins
    assert "cumulative count of the lowest modes" in spectra[0]
    assert any(label.startswith("full (sinvert") or label.startswith("full (dense")
               for label in spectra[2])
    assert any(label.startswith("c = min f(x) =") and "localised modes out" in label
               for label in soft[2])
    assert any("standard error" in label for label in dos[2])


def test_short_log_axes_get_labelled_ticks():
    """A log axis over 0.6 decades (G/B of three states) had one labelled tick: now >= 3, in
    plain numbers; a long one keeps matplotlib's powers of ten."""
    from parjam.plot import pyplot
    from parjam.plot.labels import readable_log_ticks

    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2)
    a.loglog([1e-4, 1e-2], [0.02, 0.08])
    b.loglog([1e-6, 1e2], [1e-5, 1e3])
    fig.canvas.draw()
    before = [t.get_text() for t in a.get_yticklabels() if t.get_text()]
    readable_log_ticks(fig)
    fig.canvas.draw()
    ticks = [float(t.get_text()) for t in a.get_yticklabels() if t.get_text()]
    lo, hi = a.get_ylim()
    assert len(ticks) >= 3 and all(lo <= t <= hi for t in ticks), (before, ticks)
    assert np.all(np.diff(ticks) > 0)
    long = [t.get_text() for t in b.get_yticklabels() if t.get_text()]
    assert all("10^" in t or "10^{" in t for t in long)  # untouched: $\mathdefault{10^{-4}}$
    plt.close(fig)
