"""Stochastic D(omega) by the kernel polynomial method (parjam.vib.kpm): against the dense spectra of
the reference packings, an analytic spectrum (the Jacobian 2 omega), unbiased moments, probes
independent of the rank layout, 1 vs 2 ranks, eigenvalues outside the bounds, and the CLI."""

import numpy as np
import pytest

from parjam import env
from parjam.files import h5md
from parjam.vib import hessian, kpm, observables, spectrum, translations
from parjam.errors import ParjamError

PETSc = env.petsc()
WORLD = PETSc.COMM_WORLD
SELF = PETSc.COMM_SELF
DATA = "tests/data"
REFERENCE = ["ref_d3_mono_N128_dphi1e-06", "ref_d3_mono_N128_dphi1e-03",
             "ref_d2_bi_N128_dphi1e-06", "ref_d2_bi_N128_dphi1e-03"]


def reference(name):
    s = spectrum.system_of(WORLD, h5md.read_packing(f"{DATA}/{name}.h5"))
    lam = np.load(f"{DATA}/{name}.spectrum.npz")["full"][s.d:]  # translations dropped
    return s, lam


def l1_to_dense(res, lam, bins=20):
    edges = observables.dos_edges(res.omega_max, bins)
    _, dense = observables.density_of_states(observables.frequency(lam), len(lam), edges)
    return kpm.l1_distance(res.binned(edges), dense, edges)


def tolerance(m, p):
    """Allowed L1 distance (0..2) for m moments x p probes at N' ~ 125: a floor for the bin
    discretisation of a 375-mode histogram plus a stochastic/kernel part ~ 1/sqrt(m p)."""
    return 0.06 + 2.0 / np.sqrt(m * p)


@pytest.mark.parametrize("name", REFERENCE)
def test_kpm_dos_matches_dense_reference(name):
    s, lam = reference(name)
    errors = []
    for m, p in [(64, 4), (256, 64)]:
        res = kpm.compute(WORLD, s, "full", m, p, seed=3)
        err = l1_to_dense(res, lam)
        assert err <= tolerance(m, p), (m, p, err)
        errors.append(err)
        assert np.isclose(res.cumulative(res.b), 1.0)  # normalised per mode (d N' - d)
        assert res.a < lam[0] and res.b > lam[-1]  # the bounds enclose the spectrum
    assert errors[1] < errors[0]  # more moments x probes, closer to the truth


@pytest.mark.parametrize("name", REFERENCE[1::2])
def test_plateau_height_matches_dense(name):
    s, lam = reference(name)
    res = kpm.compute(WORLD, s, "full", 256, 64, seed=5)
    d0_dense, _, window = observables.dos_summary(observables.frequency(lam), len(lam))
    d0, _, _ = kpm.dos_summary(res, plateau=window)
    assert abs(d0 / d0_dense - 1) < 0.05


def test_moments_are_unbiased():
    """Stochastic moments scatter around the exact mu_n = mean_k T_n(x_k) of the dense
    eigenvalues within a few standard errors of the probe mean."""
    s, lam = reference(REFERENCE[1])
    res = kpm.compute(WORLD, s, "full", 128, 48, seed=11)
    x = res.scaled(lam)
    exact = np.cos(np.multiply.outer(np.arange(128), np.arccos(x))).mean(axis=1)
    sem = res.probe_moments.std(axis=0, ddof=1) / np.sqrt(res.n_probes)
    assert np.all(np.abs(res.moments[1:] - exact[1:]) <= 5 * sem[1:] + 1e-12)
    # with the exact moments only the kernel remains: closer to the histogram
    edges = observables.dos_edges(res.omega_max, 20)
    _, dense = observables.density_of_states(observables.frequency(lam), len(lam), edges)
    assert kpm.l1_distance(res.binned(edges, exact), dense, edges) < 0.04


def ring(comm, n):
    """A periodic chain of n unit springs (d = 1): lambda_k = 4 sin^2(pi k / n), one exact
    zero mode (the translation), and D(omega) = 2 / (pi sqrt(4 - omega^2)) on (0, 2)."""
    i = np.arange(n)
    j = (i + 1) % n
    return hessian.assemble(comm, n, 1, i, j, np.ones((n, 1, 1)))


def test_jacobian_on_the_ring_spectrum():
    n = 1 << 16
    A = ring(WORLD, n)
    try:
        res = kpm.moments(A, 1, n - 1, "relaxed", 128, 16, seed=2)
    finally:
        A.destroy()
    w = np.linspace(0.2, 1.8, 17)
    exact = 2.0 / (np.pi * np.sqrt(4.0 - w * w))
    assert np.allclose(res.density_omega(w), exact, rtol=0.05)
    edges = np.linspace(0.0, 1.9, 20)
    F = 2.0 / np.pi * np.arcsin(edges / 2.0)  # exact cumulative in omega
    assert np.allclose(res.binned(edges)[1:], np.diff(F)[1:] / np.diff(edges)[1:], rtol=0.05)
    assert abs(res.b - 4.0) < 0.05  # Lanczos bound close to lambda_max = 4


def test_negative_eigenvalues_are_enclosed():
    """An unstable matrix (the ring shifted by -1/2: lambda = 4 sin^2(pi k/n) - 1/2): the
    Lanczos bounds enclose the negative part, and F(0) is the exact fraction below zero."""
    n = 1 << 14
    i = np.arange(n)
    A = hessian.assemble(WORLD, n, 1, i, (i + 1) % n, np.ones((n, 1, 1)), shift=-0.5)
    try:
        res = kpm.moments(A, 1, n - 1, "full", 256, 8, seed=4)
    finally:
        A.destroy()
    assert -0.6 < res.a < -0.5
    exact = 2.0 / np.pi * np.arcsin(np.sqrt(0.5) / 2.0)  # fraction with 4 sin^2 < 1/2
    assert abs(res.cumulative(0.0) - exact) < 0.01
    assert not res.fold_below_zero  # the negative modes are not binned as vibrations
    edges = np.linspace(0.0, 1.8, 10)
    assert abs(np.sum(res.binned(edges) * np.diff(edges)) - (res.cumulative(3.24) - exact)) < 0.01


def test_probes_do_not_depend_on_the_layout():
    whole = kpm.probe_values(7, 3, 0, 3 * kpm.CHUNK // 2)
    parts = [kpm.probe_values(7, 3, lo, hi) for lo, hi in
             [(0, 1000), (1000, kpm.CHUNK + 5), (kpm.CHUNK + 5, 3 * kpm.CHUNK // 2)]]
    assert np.array_equal(whole, np.concatenate(parts))
    assert set(np.unique(whole)) == {-1.0, 1.0}
    assert not np.array_equal(whole, kpm.probe_values(7, 4, 0, len(whole)))
    g = kpm.probe_values(7, 3, 0, 20000, "gaussian")
    assert abs(g.mean()) < 0.05 and abs(g.std() - 1) < 0.05


def test_translations_projected_out():
    s, _ = reference(REFERENCE[0])
    A = spectrum.dynamical_matrix(WORLD, s, "full")
    v = A.createVecRight()
    kpm.fill_probe(v, 1, 0, "gaussian")
    translations.project(v, s.d)
    for t in translations.vectors(A, s.d):
        assert abs(t.dot(v)) < 1e-12 * v.norm()
        t.destroy()
    v.destroy()
    A.destroy()


def test_one_rank_equals_world():
    """The same probes on COMM_SELF and on all ranks: the same moments to round-off (under
    mpirun -n 2 this compares 1 rank with 2)."""
    _, (pack,) = __import__("parjam.pack.packing", fromlist=["make_jammed"]).make_jammed(
        3, 128, [1e-2], seed=4)
    one = kpm.compute(SELF, spectrum.system_of(SELF, pack), "full", 200, 6, seed=9)
    world = kpm.compute(WORLD, spectrum.system_of(WORLD, pack), "full", 200, 6, seed=9)
    assert np.allclose(one.a, world.a, rtol=1e-10) and np.allclose(one.b, world.b, rtol=1e-10)
    assert np.abs(one.probe_moments - world.probe_moments).max() < 1e-10
    edges = observables.dos_edges(one.omega_max, 30)
    assert np.abs(one.binned(edges) - world.binned(edges)).max() < 1e-9


def test_eigenvalues_outside_bounds_are_refused():
    s, lam = reference(REFERENCE[1])
    with pytest.raises(ParjamError, match="outside the bounds"):
        kpm.compute(WORLD, s, "full", 128, 2, seed=0, bounds=(0.5 * lam[-1], 1.01 * lam[-1]))
    with pytest.raises(ParjamError):
        kpm.compute(WORLD, s, "full", 1, 2)


@pytest.mark.serial
def test_dos_kpm_cli(tmp_path):
    import subprocess
    import sys

    import h5py

    out = tmp_path / "kpm.h5"
    files = [f"{DATA}/{REFERENCE[1]}.h5", f"{DATA}/{REFERENCE[0]}.h5"]
    cmd = [sys.executable, "-m", "parjam", "dos", "--method", "kpm", *files, "--bins", "20",
           "--moments", "128", "--probes", "8", "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    with h5py.File(out) as f:
        dens = f["dos/density"][()]
        edges = f["dos/edges"][()]
        assert f["dos"].attrs["method"] == "kpm" and f["dos"].attrs["n_files"] == 2
        assert f["dos/density_error"].shape == dens.shape
    assert abs(np.sum(dens * np.diff(edges)) - 1) < 0.02
    bad = subprocess.run(cmd[:-2] + ["--kpm-bounds", "3,1", "--out", str(tmp_path / "x.h5")],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "a < b" in bad.stderr
    assert not (tmp_path / "x.h5").exists()
