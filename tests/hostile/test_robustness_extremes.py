"""Numerical extremes, with tolerances that can fail: dphi = 1e-8 and dphi = 1, alpha = 2, 2.5
and 3, d = 2 and 3, N = 16 and up, a wide polydispersity; the crystallisation of monodisperse 2D
packings detected; zero modes (rattlers, translations, a hypostatic network) counted and never
taken for vibrations; unstable states flagged; overlaps of ~1e-8 against a 50-digit evaluation.

Packings are built on COMM_SELF (every rank of the MPI pass builds the same ones)."""

import contextlib
import dataclasses
import io
import os
import shutil
import tempfile

import h5py
import mpmath
import numpy as np
import pytest

from parjam.vib.dense import dense_matrix
from parjam import cli, env
from parjam.net import network, order, potential
from parjam.pack import kernels
from parjam.vib import spectrum
from parjam.pack.ensemble import REL_FORCE_WARN, quality_checks
from parjam.errors import ParjamError
from parjam.files.h5md import observable, read_packing, write_packing
from parjam.pack.packing import PHI_MAX, make_jammed, random_packing
from parjam.net.system import Packing
from conftest import ROOT

PETSc = env.petsc()
SELF = PETSc.COMM_SELF
ISOSTATIC = os.path.join(ROOT, "tests", "data", "soft_d2_N64_m0.h5")  # 2D, dphi = 1e-8, +0
FTOL = 1e-13


def _check_state(pack, dphi):
    net = network.analyze(pack)
    assert net.max_force <= FTOL, net.max_force
    assert np.all((pack.pos >= 0) & (pack.pos < pack.L))
    assert net.excess >= 0  # a jammed packing is never hypostatic
    assert net.pressure > 0
    return net


# --- compression extremes, dimensions, sizes ---------------------------------------------------
@pytest.mark.parametrize("d,n", [(2, 16), (2, 32), (3, 32)])
def test_dphi_1e8_and_1(d, n):
    """Both ends of the ladder jam and balance forces; dphi = 1 puts phi far above the phi_c
    search's PHI_MAX guard, which must not reject it (it only bounds the phi_c search)."""
    phi_c, (tiny, huge) = make_jammed(d, n, [1e-8, 1.0], seed=1)
    net_tiny = _check_state(tiny, 1e-8)
    net_huge = _check_state(huge, 1.0)
    assert huge.phi == pytest.approx(phi_c + 1.0, abs=1e-12) and huge.phi > PHI_MAX[d]
    assert tiny.phi == pytest.approx(phi_c + 1e-8, abs=1e-14)
    assert net_tiny.excess <= 2  # at dphi = 1e-8 the network is (nearly) isostatic
    assert net_huge.z > 2 * d + 1  # far above isostatic
    assert net_tiny.summary()["max_force_rel"] < REL_FORCE_WARN


@pytest.mark.parametrize("alpha,n", [(2.5, 32), (3.0, 16)])
def test_hertz_and_alpha_3(alpha, n):
    """p ~ dphi^(alpha - 1) between dphi = 1e-4 and 1e-2 (one configuration: exponent within
    0.1); at dphi = 1e-8 the contact forces are ~dphi^(alpha-1) ~ 1e-16, far below the absolute
    tolerance: the returned state is balanced further, relative to its contact forces
    (parjam.pack.packing.Jammer.polish), and a poor balance would still be flagged."""
    phi_c, packs = make_jammed(2, n, [1e-8, 1e-4, 1e-2], seed=2, alpha=alpha)
    nets = [_check_state(p, dp) for p, dp in zip(packs, [1e-8, 1e-4, 1e-2])]
    slope = np.log(nets[2].pressure / nets[1].pressure) / np.log(100.0)
    assert abs(slope - (alpha - 1.0)) < 0.1, slope
    rel = [net.summary()["max_force_rel"] for net in nets]
    assert rel[2] < 1e-9
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        quality_checks(packs[0], nets[0], "dphi 1e-8")
    assert ("force balance only" in err.getvalue()) == (rel[0] > REL_FORCE_WARN)
    assert rel[0] < REL_FORCE_WARN  # alpha = 3, N = 16: 1.5e-3 before the polish


def test_wide_polydispersity():
    """Diameters uniform in [1, 4] (2D, N = 64): jams, balances forces, isostatic near phi_c."""
    phi_c, (near, far) = make_jammed(2, 64, [1e-6, 1e-2], seed=3, dispersity="poly", ratio=4.0)
    assert near.diam.max() / near.diam.min() > 3.5
    assert 0.75 < phi_c < 0.92
    assert _check_state(near, 1e-6).excess <= 2
    assert _check_state(far, 1e-2).excess > 0


# --- crystallisation -------------------------------------------------------------------------
def _quench_2d(dispersity, phi=0.88, n=128, seed=4):
    """A random 2D start minimised at fixed phi (above phi_c for both mixtures)."""
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer

    jam = Jammer(SELF, random_packing(2, n, phi, dispersity=dispersity,
                                      rng=member_rng(seed, 0)))
    try:
        return jam.at_phi(phi, "quench").pack
    finally:
        jam.destroy()


def test_monodisperse_2d_crystallises_and_is_flagged():
    """A monodisperse 2D packing orders (local hexatic order > 0.7: 0.87-0.90 for jammed N = 256
    ensembles, ~0.85 for this quench); the bidisperse 1:1.4 mixture stays amorphous (0.56-0.57);
    the flag and the order parameters go to stderr and to /observables."""
    mono, bi = _quench_2d("mono"), _quench_2d("bi")
    local_mono, _ = order.hexatic_order(mono)
    local_bi, _ = order.hexatic_order(bi)
    assert local_mono > order.CRYSTAL_THRESHOLD > local_bi
    assert local_bi < 0.65
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        extra = quality_checks(mono, network.analyze(mono), "mono")
        quality_checks(bi, network.analyze(bi), "bi")
    assert err.getvalue().count("crystallised") == 1 and "mono:" in err.getvalue()
    assert extra["crystallised"] == 1
    tmp = tempfile.mkdtemp()
    try:
        path = os.path.join(tmp, "mono.h5")
        write_packing(path, mono, network.analyze(mono), {}, observables=extra)
        with h5py.File(path) as f:
            assert observable(f, "crystallised") == 1
            assert observable(f, "hexatic_order_local") == pytest.approx(local_mono)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def test_hexatic_order_of_a_triangular_lattice_is_one():
    a, m = 1.0, 8  # 8 x 8 triangular lattice, nearest neighbours at 0.98 sigma (slight overlap)
    rows = [[(i + 0.5 * (j % 2)) * a, j * a * np.sqrt(3) / 2] for j in range(m) for i in range(m)]
    pos = np.array(rows)
    L = m * a  # not commensurate in y: the seam costs a few neighbours, order stays ~1
    pack = Packing(pos, np.full(m * m, 1.02), L)
    local, _ = order.hexatic_order(pack)
    assert local > 0.9


# --- zero modes --------------------------------------------------------------------------------
def _without_contacts(system, q, seed=0):
    """The system (on one rank: both half-edges of every contact) without q random contacts."""
    once = np.flatnonzero(system.i < system.j)
    cut = once[np.random.default_rng(seed).choice(len(once), q, replace=False)]
    pairs = set(zip(system.i[cut].tolist(), system.j[cut].tolist()))
    keep = np.array([(min(a, b), max(a, b)) not in pairs
                     for a, b in zip(system.i.tolist(), system.j.tolist())], bool)
    return dataclasses.replace(system, i=system.i[keep], j=system.j[keep], rij=system.rij[keep],
                               r=system.r[keep], sigma=system.sigma[keep],
                               n_contacts=system.n_contacts - q)


def _dense_zero_count(system, kind, zero_tol):
    """Independent count: eigenvalues of Q^T H Q (Q: the complement of the translations)."""
    H = dense_matrix(system.gathered(SELF), kind)
    n, d = system.n, system.d
    T = np.zeros((n * d, d))
    for a in range(d):
        T[a::d, a] = 1.0 / np.sqrt(n)
    Q = np.linalg.qr(np.hstack([T, np.eye(n * d)]))[0][:, d:n * d]
    lam = np.linalg.eigvalsh(Q.T @ H @ Q)
    return int(np.sum(np.abs(lam) <= zero_tol)), int(np.sum(lam < -zero_tol))


@pytest.mark.parametrize("q", [2, 4])
def test_hypostatic_network_zero_modes_are_counted(q):
    """Cutting q contacts of an isostatic network leaves q - 1 floppy modes (the first cut only
    removes the state of self-stress).  The relaxed matrix: counted as zero modes by dense and
    shift-and-invert, equal to an independent dense count, and kept out of the vibrations.  The
    full matrix: the stress term makes them negative, so the packing is flagged unstable."""
    system = _without_contacts(spectrum.system_of(SELF, read_packing(ISOSTATIC)), q)
    for method in ("dense", "sinvert"):
        relaxed = spectrum.compute(SELF, system, "relaxed", k=8, method=method)
        zero, neg = _dense_zero_count(system, "relaxed", relaxed.zero_tol)
        assert relaxed.n_zero == zero == q - 1 and neg == 0
        assert relaxed.complete and not relaxed.unstable
        assert np.sum(relaxed.physical) == 8 - (q - 1)
        assert np.all(relaxed.eigenvalue[relaxed.physical] > relaxed.zero_tol)
        full = spectrum.compute(SELF, system, "full", k=8, method=method)
        assert full.unstable and full.n_negative == q - 1
        assert full.n_negative == _dense_zero_count(system, "full", full.zero_tol)[1]
    with pytest.raises(ParjamError, match="inside the zero cluster"):
        spectrum.compute(SELF, system, "relaxed", k=8, method="sinvert", target=0.0)


def _run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def test_rattlers_translations_and_hypostatic_files_in_modes_cli(shared_tmp):
    """`parjam modes` accounts for every zero mode: rattlers removed (their d N_r zero modes
    excluded), the d translations deflated, no zero mode left among the vibrations; a packing
    made hypostatic (one particle shrunk out of its contacts) is refused with its floppy count."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    path = os.path.join(shared_tmp, "zero-modes.h5")
    out = os.path.join(shared_tmp, "zero-modes.spec.h5")
    if comm.Get_rank() == 0:
        shutil.copy(ISOSTATIC, path)
    comm.Barrier()
    rc, _, err = _run(["modes", path, "--k", "20", "--method", "dense", "--out", out, "-q"])
    assert rc == 0, err
    net = network.analyze(read_packing(path))
    with h5py.File(out) as f:
        a = dict(f["modes"].attrs)
        lam = f["modes/eigenvalue"][()]
    assert a["n_rattlers"] == net.n_rattlers > 0
    assert a["n_translations"] == 2 and a["n_zero_modes"] == 0
    assert a["n_modes_total"] == 2 * net.n_active - 2
    assert lam.min() > a["zero_tol"]
    comm.Barrier()
    if comm.Get_rank() == 0:
        with h5py.File(path, "a") as f:  # shrink the best-connected particle out of contact
            diam = f["particles/all/diameter"][()]
            k = np.bincount(net.contacts.i, minlength=len(diam)) + np.bincount(
                net.contacts.j, minlength=len(diam))
            diam[np.argmax(k)] *= 0.999
            del f["particles/all/diameter"]
            f["particles/all/diameter"] = diam
    comm.Barrier()
    hypo = network.analyze(read_packing(path))
    assert hypo.excess < 0
    rc, _, err = _run(["modes", path, "--k", "5", "--out", out + "2", "-q"])
    assert rc == 3 and not os.path.exists(out + "2")
    if comm.Get_rank() == 0:
        assert f"at least {-hypo.excess} floppy mode(s)" in err


def test_unminimised_packing_is_flagged_unstable(shared_tmp):
    """A packing stopped far from its energy minimum (random overlapping positions at phi = 1.2,
    never minimised) has negative eigenvalues of the full matrix: `parjam modes` warns and
    records it."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    path = os.path.join(shared_tmp, "raw.h5")
    out = os.path.join(shared_tmp, "raw.spec.h5")
    if comm.Get_rank() == 0:
        pack = random_packing(2, 64, 1.2, rng=np.random.default_rng(7))
        write_packing(path, pack, network.analyze(pack), {})
    comm.Barrier()
    rc, _, err = _run(["modes", path, "--k", "10", "--method", "sinvert", "--out", out, "-q"])
    assert rc in (0, 4), err
    with h5py.File(out) as f:
        assert f["modes"].attrs["unstable"] and f["modes"].attrs["n_negative"] > 0
    if comm.Get_rank() == 0:
        assert "unstable packing" in err


# --- round-off -----------------------------------------------------------------------------------
mpmath.mp.dps = 50


def _exact_overlap(xi, xj, si, sj, L):
    """1 - r/sigma of the stored float64 values, minimum image, in 50-digit arithmetic."""
    Lm = mpmath.mpf(L)
    s2 = mpmath.mpf(0)
    for a in range(len(xi)):
        dr = mpmath.mpf(xj[a]) - mpmath.mpf(xi[a])
        dr -= mpmath.nint(dr / Lm) * Lm
        s2 += dr * dr
    sigma = (mpmath.mpf(si) + mpmath.mpf(sj)) / 2
    return 1 - mpmath.sqrt(s2) / sigma


@pytest.mark.parametrize("name", ["soft_d2_N64_m0.h5", "soft_d2_N1024_m0.h5",
                                  "soft_d3_N512_m0.h5"])
def test_overlaps_at_1e8_keep_relative_precision(name):
    """At dphi = 1e-8 the overlaps are ~1e-8 of a diameter.  Against a 50-digit evaluation of the
    stored positions (in [0, L), minimum image), the float64 overlaps have absolute errors below
    5e-16 for every contact, also those that wrap through the box (L = 7.5 to 37.6), so those of
    5e-9 and more keep relative precision 1e-7, and so do their contact forces.  (Before the
    exact boundary shift of parjam.net.system.pair_separation the wrapped contacts of the L = 37.6
    box had absolute errors of 3.4e-15: relative 4.5e-7 at these overlaps.)"""
    pack = read_packing(os.path.join(ROOT, "tests", "data", name))
    c = network.find_contacts(pack)
    delta = potential.overlap(c.r, c.sigma)
    force = np.abs(potential.dV(c.r, c.sigma, pack.alpha, pack.eps))
    wraps = np.any(np.abs(pack.pos[c.j] - pack.pos[c.i]) > pack.L / 2, axis=1)
    assert wraps.sum() > 3 and np.median(delta) < 2e-8
    rng = np.random.default_rng(0)  # every wrapped contact and 200 others
    pick = np.concatenate([np.nonzero(wraps)[0],
                           rng.choice(np.nonzero(~wraps)[0], min(200, (~wraps).sum()),
                                      replace=False)])
    for k in pick:
        exact = _exact_overlap(pack.pos[c.i[k]], pack.pos[c.j[k]], pack.diam[c.i[k]],
                               pack.diam[c.j[k]], pack.L)
        abs_err = abs(float(mpmath.mpf(delta[k]) - exact))
        assert abs_err < 5e-16, (k, wraps[k], abs_err)
        if delta[k] >= 5e-9:
            assert abs_err / float(exact) < 1e-7
            f_exact = exact / ((mpmath.mpf(pack.diam[c.i[k]]) + pack.diam[c.j[k]]) / 2)
            assert abs(force[k] - float(f_exact)) / float(f_exact) < 1e-7


@pytest.mark.parametrize("L", [10.0, 40.0])
def test_kernel_forces_across_the_boundary(L):
    """Two particles overlapping by ~1e-8 through the periodic boundary (one near L, one near 0):
    the compiled kernel's forces against the 50-digit value of the stored positions, relative
    1e-7 at L = 10 and 40 (absolute 5e-16: the boundary shift is exact)."""
    rng = np.random.default_rng(int(L))
    for _ in range(5):
        u = rng.normal(size=2)
        u /= np.linalg.norm(u)
        gap = 1.0 - 1e-8  # centre distance for unit diameters
        a = np.array([L - 0.3, L * 0.5]) if abs(u[0]) > 0.5 else np.array([L * 0.5, L - 0.3])
        b = a + gap * u
        pos = np.mod(np.stack([a, b]), L)
        diam = np.ones(2)
        out = np.zeros((2, 2))
        pi, pj = np.array([0], np.int64), np.array([1], np.int64)
        kernels.pair_forces(pi, pj, np.ascontiguousarray(pos), diam, L, 2.0, 1.0, 0, 2, out)
        exact = _exact_overlap(pos[0], pos[1], 1.0, 1.0, L)  # harmonic: |F| = overlap
        assert 5e-9 < float(exact) < 2e-8
        fmag = np.linalg.norm(out[1])
        assert abs(fmag - float(exact)) < 5e-16
        assert abs(fmag - float(exact)) / float(exact) < 1e-7
        assert np.allclose(out[0], -out[1], rtol=0, atol=1e-22)
