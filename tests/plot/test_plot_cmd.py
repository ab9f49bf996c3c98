"""``parjam plot`` (parjam.commands.plot) and the paper's figures and fits (parjam.plot.paper,
parjam.study.fits): known power laws recovered with bootstrap errors, a synthetic results
directory and a tiny real ``parjam run`` drawn to valid PNGs of the expected size, the single
result files of other commands, and bad input (one-line error, exit 2, no PNG, no temporary
file).  Serially and under mpirun -n 2 (rank 0 draws, the other ranks return the same code)."""

import glob
import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from conftest import DATA, ROOT, subprocess_env
from parjam import cli, env
from parjam.study.fits import bootstrap, fit_eq33, fit_power
from parjam.plot import atomic_png, paper

MPI = env.petsc().COMM_WORLD.tompi4py()
RANK = MPI.Get_rank()
REF2D = os.path.join(DATA, "ref_d2_bi_N128_dphi1e-03.h5")
REF2D_LOW = os.path.join(DATA, "ref_d2_bi_N128_dphi1e-06.h5")
SOFT2D = os.path.join(DATA, "soft_d2_N128_m0.h5")

# the laws of the synthetic summary: dz = C0 p^(1/2), omega*_relaxed = K dz,
# omega_AM^2 = A1 dz^2 - A2 p with A1 = K^2
C0, K, A2 = 14.0, 0.25, 3.0
DPHI = [1e-5, 1e-4, 1e-3, 1e-2, 1e-1]


def png_size(path):
    """(width, height) of a PNG that decodes completely."""
    from PIL import Image

    with Image.open(path) as im:
        assert im.format == "PNG"
        im.load()
        return im.size


def inches(width, height, dpi=150):
    """Pixel size of a figure of width x height inches drawn at dpi (matplotlib rounds)."""
    return (int(round(width * dpi)), int(round(height * dpi)))


def leftovers(directory):
    """Temporary files of atomic writes left in a directory (there must be none)."""
    return glob.glob(os.path.join(directory, ".*tmp*"))


# --------------------------------------------------------------------------- fits

def test_fit_power_recovers_the_exponent_with_a_bootstrap_error():
    rng = np.random.default_rng(1)
    x = np.geomspace(1e-5, 1e-1, 6)
    X = x * (1 + 0.05 * rng.standard_normal((5, 6)))  # members x states, x scattered too
    Y = 2.5 * X**0.5 * (1 + 0.03 * rng.standard_normal((5, 6)))
    f = fit_power(X, Y, n_boot=400)
    assert f["exponent"] == pytest.approx(0.5, abs=0.01)
    assert f["prefactor"] == pytest.approx(2.5, rel=0.1)
    assert 0 < f["exponent_err"] < 0.01 and f["prefactor_err"] > 0
    assert (f["members"], f["points"]) == (5, 6)
    assert fit_power(X, Y, n_boot=400) == f  # seeded: reproducible
    # a NaN member is skipped in the means, a non-positive mean is left out of the fit
    Y2 = Y.copy()
    Y2[0, 2] = np.nan
    Y2[:, 0] = -1.0
    g = fit_power(X, Y2, n_boot=50)
    assert g["exponent"] == pytest.approx(0.5, abs=0.01) and g["points"] == 6
    # exact data: zero error; fewer than two usable points: NaN
    exact = fit_power(np.tile(x, (3, 1)), np.tile(x**-1.5, (3, 1)), n_boot=50)
    assert exact["exponent"] == pytest.approx(-1.5, abs=1e-12) and exact["exponent_err"] < 1e-12
    assert np.isnan(fit_power(X[:, :1], Y[:, :1], n_boot=10)["exponent"])
    # an x shared by all members (a protocol's dphi) as one row: the same fit as the full table
    shared = fit_power(x, Y, n_boot=100)
    assert shared == fit_power(np.tile(x, (5, 1)), Y, n_boot=100)
    assert shared["exponent"] == pytest.approx(0.5, abs=0.02) and shared["members"] == 5


def test_fit_eq33_separates_a1_and_a2():
    dz = np.geomspace(0.05, 1.0, 4) * np.ones((3, 1))
    p = (dz / C0) ** 2 * 1.02
    ws2 = K**2 * dz**2
    w2 = K**2 * dz**2 - A2 * p
    f = fit_eq33(w2, ws2, dz, p, n_boot=50)
    assert f["A1"] == pytest.approx(K**2, rel=1e-12)
    assert f["A2"] == pytest.approx(A2, rel=1e-10) and f["A2_err"] < 1e-10
    assert np.allclose(f["A2_per_state"], A2, rtol=1e-10)


def test_bootstrap_resamples_members():
    best, boots = bootstrap(lambda rows: np.array([len(set(rows)), rows.sum()]), 6, n_boot=200)
    assert list(best) == [6, 15]
    assert boots.shape == (200, 2) and boots[:, 0].max() <= 6 and boots[:, 0].min() < 6


# --------------------------------------------------------------------------- a synthetic summary

def write_summary(path, members=4, seed=0):
    """A summary file in the layout of parjam.study.summary.write_summary with known laws."""
    rng = np.random.default_rng(seed)
    labels = ["phi_c"] + [f"dphi{x:.1e}" for x in DPHI]
    with h5py.File(path, "w") as f:
        f.attrs.update({"system": "synthetic-N512", "d": 3, "n": 512, "members": members,
                        "dispersity": "mono", "alpha": 2.0})
        f.attrs["states"] = np.array([s.encode() for s in labels])
        for x, lab in zip(DPHI, labels[1:]):
            p = 2 * x * (1 + 0.05 * rng.standard_normal(members))
            dz = C0 * np.sqrt(p) * (1 + 0.02 * rng.standard_normal(members))
            net = f.create_group(f"{lab}/network")
            net["pressure"], net["dz_iso"] = p, dz
            net["N_active"] = np.full(members, 500.0)
            rel = f.create_group(f"{lab}/spectrum/relaxed")
            rel["omega_star"] = K * dz
            full = f.create_group(f"{lab}/spectrum/full")
            full["omega_star"] = np.sqrt(K**2 * dz**2 - A2 * p)
            w = np.linspace(0.05, 2, 20)
            dos = full.create_group("dos")
            dos["omega"], dos["density"] = w, 0.4 * np.ones_like(w)
            dos["density_error"] = 0.01 * np.ones_like(w)


@pytest.fixture(scope="module")
def synthetic(shared_tmp):
    root = os.path.join(shared_tmp, "synthetic")
    if RANK == 0:
        os.makedirs(os.path.join(root, "paper-3d"))
        write_summary(os.path.join(root, "paper-3d", "summary-synthetic.h5"))
    MPI.Barrier()
    return root


def test_results_directory_fits_and_figures(synthetic, shared_tmp, capsys):
    img = os.path.join(shared_tmp, "img-synthetic")
    fits_path = os.path.join(shared_tmp, "fits-synthetic.json")
    assert cli.main(["plot", synthetic, "--img", img, "--json", fits_path]) == 0
    fits = json.load(open(fits_path))
    diag, sans = fits["diag/synthetic-N512"], fits["sans/synthetic-N512"]
    assert diag["exponent"] == pytest.approx(0.5, abs=0.02)
    assert diag["prefactor"] == pytest.approx(C0, rel=0.1)
    assert 0 < diag["exponent_err"] < 0.02 and diag["points"] == 5
    assert sans["exponent"] == pytest.approx(1.0, abs=0.02) and sans["points"] == 4
    eq = fits["eq33/synthetic-N512"]
    assert eq["A1"] == pytest.approx(K**2, rel=0.01) and eq["A2"] == pytest.approx(A2, rel=0.1)
    assert fits["size/synthetic-N512"] == {"N": 512, "members": 4}
    # only the figures with data, at their figure size x 150 dpi
    assert sorted(os.listdir(img)) == ["repro_diag.png", "repro_eq33.png", "repro_fig1.png",
                                       "repro_sans.png"]
    assert png_size(os.path.join(img, "repro_sans.png")) == inches(4.6, 3.6)
    assert png_size(os.path.join(img, "repro_diag.png")) == inches(4.8, 3.7)
    assert png_size(os.path.join(img, "repro_fig1.png")) == inches(4.6, 3.4)  # one panel
    out = capsys.readouterr().out
    if RANK == 0:
        assert "no data for: compare, trans, fluct, hertz, softmodes" in out
        assert "diag/synthetic-N512: exponent 0.5" in out


def test_one_figure_to_out_and_the_script_wrapper(synthetic, shared_tmp):
    """--figures diag --out: one PNG; diag fits Eq. (33) for its stability line itself.
    scripts/reproduce.py gives the same fits and bytes as parjam plot."""
    png = os.path.join(shared_tmp, "diag-only.png")
    fits_path = os.path.join(shared_tmp, "fits-diag.json")
    assert cli.main(["plot", synthetic, "--figures", "diag", "--out", png, "--json", fits_path,
                     "-q"]) == 0
    assert png_size(png) == inches(4.8, 3.7)
    fits = json.load(open(fits_path))
    assert {k.split("/")[0] for k in fits} == {"diag", "eq33", "eq33_relaxed_ratio", "size"}
    if RANK == 0:
        sys.path.insert(0, os.path.join(ROOT, "scripts"))
        try:
            import reproduce
        finally:
            sys.path.pop(0)
        img = os.path.join(shared_tmp, "img-script")
        js = os.path.join(shared_tmp, "fits-script.json")
        reproduce.main(["--results", synthetic, "--img", img, "--json", js])
        ref = os.path.join(shared_tmp, "img-synthetic")
        if os.path.isdir(ref):  # drawn by the previous test
            for name in os.listdir(ref):
                with open(os.path.join(ref, name), "rb") as a, \
                        open(os.path.join(img, name), "rb") as b:
                    assert a.read() == b.read(), name
        assert json.load(open(js))["diag/synthetic-N512"] == fits["diag/synthetic-N512"]
    MPI.Barrier()


# --------------------------------------------------------------------------- a tiny real run

TINY = """
[[system]]
d = 2
N = 64
dispersity = "bi"
[protocol]
dphi = [1e-4, 1e-3, 1e-2, 1e-1]
[ensemble]
members = 2
seed = 3
[observables]
contacts = true
dos = { matrices = ["full", "relaxed"], bins = 10 }
omega_star = { matrices = ["relaxed", "full"] }
"""


def test_a_real_run_directory(shared_tmp):
    """The summary files of parjam run (directly in --out) give fig1, compare, sans, eq33, diag;
    a summary file works as input too."""
    scene = os.path.join(shared_tmp, "tiny.toml")
    if RANK == 0:
        with open(scene, "w") as fh:
            fh.write(TINY)
    MPI.Barrier()
    out = os.path.join(shared_tmp, "tiny-run")
    assert cli.main(["run", scene, "--out", out, "-q"]) == 0
    img = os.path.join(shared_tmp, "img-tiny")
    fits_path = os.path.join(shared_tmp, "fits-tiny.json")
    assert cli.main(["plot", out, "--img", img, "--json", fits_path, "-q"]) == 0
    assert sorted(os.listdir(img)) == sorted(f"repro_{n}.png" for n in
                                             ("fig1", "compare", "sans", "eq33", "diag"))
    for name in os.listdir(img):
        w, h = png_size(os.path.join(img, name))
        assert 600 < w < 750 and 480 < h < 570  # 150 dpi
    fits = json.load(open(fits_path))
    assert 0.2 < fits["diag/d2-bi-N64"]["exponent"] < 0.8  # dz ~ p^(1/2), two tiny members
    assert fits["size/d2-bi-N64"] == {"N": 64, "members": 2}
    summary = glob.glob(os.path.join(out, "summary-*.h5"))[0]
    png = os.path.join(shared_tmp, "tiny-compare.png")
    assert cli.main(["plot", summary, "--figures", "compare", "--out", png, "-q"]) == 0
    assert png_size(png) == inches(4.6, 3.4)


# --------------------------------------------------------------------------- single files

@pytest.fixture(scope="module")
def result_files(shared_tmp):
    """Small files of parjam modes, dos, softmodes and moduli (2D, N = 128)."""
    d = os.path.join(shared_tmp, "files")
    q = ["-q"]
    assert cli.main(["modes", REF2D, "--k", "20", "--out", f"{d}/spec.h5"] + q) == 0
    assert cli.main(["modes", REF2D_LOW, "--k", "20", "--out", f"{d}/spec2.h5"] + q) == 0
    assert cli.main(["dos", f"{d}/spec.h5", f"{d}/spec2.h5", "--bins", "8",
                     "--out", f"{d}/dos.h5"]) == 0
    assert cli.main(["softmodes", SOFT2D, "--cut", "x=0.5", "--out", f"{d}/soft.h5"] + q) == 0
    assert cli.main(["moduli", REF2D, "--out", f"{d}/mod1.h5"] + q) == 0
    assert cli.main(["moduli", REF2D_LOW, "--out", f"{d}/mod2.h5"] + q) == 0
    return d


@pytest.mark.parametrize("inputs, extra, size", [
    (["spec.h5", "spec2.h5"], [], (13, 3.8)),  # inches, drawn at 150 dpi
    (["dos.h5"], [], (5, 3.8)),
    (["soft.h5"], [], (9.5, 3.6)),
    (["mod1.h5", "mod2.h5"], [], (9.5, 3.8)),
    ([SOFT2D], ["--figures", "softfig", "--ncut", "8"], (7.5, 7.5)),
    ([SOFT2D], ["--figures", "figs"], (10, 5.6)),
])
def test_single_result_files(result_files, shared_tmp, inputs, extra, size):
    png = os.path.join(shared_tmp, "single", f"{os.path.basename(inputs[0])}-{len(extra)}.png")
    args = [p if os.path.isabs(p) else os.path.join(result_files, p) for p in inputs]
    assert cli.main(["plot", *args, "--out", png, "-q", *extra]) == 0
    assert png_size(png) == inches(*size)
    assert not leftovers(os.path.dirname(png))


# --------------------------------------------------------------------------- bad input

BAD = [
    (["{tmp}/missing.h5", "--out", "{out}"], "missing.h5: no such file or directory"),
    (["{notes}", "--out", "{out}"], "not an HDF5 file"),
    (["{files}/spec.h5", "--figures", "sans", "--out", "{out}"],
     "unknown figure 'sans' for a spectrum file: choose from spectra"),
    (["{synthetic}", "--figures", "fig1,bogus", "--img", "{tmp}/bad-img"],
     "unknown figure 'bogus' for results"),
    (["{synthetic}", "--figures", "trans", "--img", "{tmp}/bad-img"],
     "no results for figure trans"),
    (["{synthetic}", "--out", "{out}"], "--out takes one figure"),
    (["{files}/spec.h5", "{files}/dos.h5", "--out", "{out}"], "the inputs mix kinds"),
    (["{files}", "--img", "{tmp}/bad-img"], "no summary-*.h5 of parjam run"),
    (["{files}/spec.h5", "--out", "{tmp}/x.jpg"], "must end in .png"),
    (["{files}/spec.h5", "--out", "{out}", "--json", "{tmp}/f.json"], "--json is for results"),
    ([REF2D.replace("d2_bi", "d3_mono"), "--figures", "figs", "--out", "{out}"],
     "draw 2D packings"),
    # fails while drawing (too few contacts on the plane): the temporary PNG is removed
    ([SOFT2D, "--figures", "softfig", "--ncut", "500", "--out", "{out}"],
     "crosses only"),
]


@pytest.mark.parametrize("args, message", BAD)
def test_bad_input_one_line_exit_2_no_png(result_files, synthetic, shared_tmp, capsys, args,
                                          message):
    tmp = os.path.join(shared_tmp, "bad")
    notes = os.path.join(tmp, "notes.h5")
    if RANK == 0:
        os.makedirs(tmp, exist_ok=True)
        with open(notes, "w") as fh:
            fh.write("not hdf5\n")
    MPI.Barrier()
    out = os.path.join(tmp, "out.png")
    fill = {"tmp": tmp, "out": out, "notes": notes, "files": result_files,
            "synthetic": synthetic}
    capsys.readouterr()
    assert cli.main(["plot"] + [a.format(**fill) for a in args]) == 2
    err = capsys.readouterr().err
    if RANK == 0:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("parjam: error: "), err
        assert message in lines[0], err
    else:
        assert err == ""
    assert not os.path.exists(out) and not os.path.exists(os.path.join(tmp, "bad-img"))
    assert not leftovers(tmp)


def test_atomic_png_leaves_nothing_on_failure(shared_tmp):
    if RANK != 0:
        return
    path = os.path.join(shared_tmp, "atomic", "a.png")
    with pytest.raises(RuntimeError):
        with atomic_png(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(b"\x89PNG half")
            raise RuntimeError("drawing failed")
    assert os.listdir(os.path.dirname(path)) == []
    with atomic_png(path) as tmp:
        assert tmp.endswith(".png") and os.path.dirname(tmp) == os.path.dirname(path)
        with open(tmp, "wb") as fh:
            fh.write(b"done")
    assert os.listdir(os.path.dirname(path)) == ["a.png"]


def test_every_figure_has_a_check_and_a_docstring():
    assert list(paper.FIGURES) == ["fig1", "compare", "sans", "trans", "eq33", "diag", "fluct",
                                   "hertz", "softmodes"]
    for f in paper.FIGURES.values():
        assert f.group in paper.SCENES and f.draw.__doc__ and not f.needs({"attrs": {
            "states": np.array([b"phi_c"]), "d": 3, "n": 8, "members": 1, "system": "x"}})


@pytest.mark.serial
def test_rank_0_failing_ends_the_mpi_job(tmp_path):
    """Under mpirun -n 2 an error on rank 0 (the only rank that draws) ends both ranks promptly
    with its one-line message, no hang."""
    r = subprocess.run(["mpirun", "--oversubscribe", "-n", "2", sys.executable, "-m", "parjam",
                        "plot", str(tmp_path / "none.h5"), "--out", str(tmp_path / "x.png")],
                       cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("parjam: error:") == 1 and "none.h5: no such file" in r.stderr
    assert not os.listdir(tmp_path)
