"""Spectra of the dynamical matrices: SLEPc shift-and-invert and slicing against dense LAPACK
and the independent reference spectra, deflation of the translations, 1 vs 2 ranks, per-mode
observables, the stress-term physics of Section IV, and bad input."""

import numpy as np
import pytest

from parjam import cli, env
from parjam.files import h5md
from parjam.net import network
from parjam.vib import observables, solver_choice, spectrum
from parjam.errors import ParjamError, UnjammedError
from parjam.pack.packing import make_jammed, random_packing
from parjam.net.system import Packing
from parjam.testing.reference import case, dense_system
from parjam.vib.dense import count_below_dense

PETSc = env.petsc()
WORLD = PETSc.COMM_WORLD
DATA = "tests/data"
REFERENCE = ["ref_d3_mono_N128_dphi1e-06", "ref_d3_mono_N128_dphi1e-03",
             "ref_d2_bi_N128_dphi1e-06", "ref_d2_bi_N128_dphi1e-03"]


@pytest.fixture(scope="module", params=[3, 2], ids=["3d", "2d"])
def jammed(request):
    """N = 256 at dphi = 1e-2 (3D mono, 2D bidisperse), the same on every rank: its system on
    the ranks and its dense reference."""
    _, (pack,) = make_jammed(request.param, 256, [1e-2], seed=1)
    return case(pack)


@pytest.fixture(scope="module")
def dense_spectra(jammed):
    """All eigenvalues of the undeflated dense matrices (numpy), translations included."""
    return {kind: np.linalg.eigvalsh(jammed.matrix(kind))
            for kind in ("full", "relaxed")}


def deflation_basis(n, d):
    """Orthonormal basis of the complement of the translations (complete QR): an independent
    way to deflate, against the Hotelling shift of the dense method."""
    T = np.zeros((n, d, d))
    T[:, np.arange(d), np.arange(d)] = 1.0
    Q, _ = np.linalg.qr(T.reshape(n * d, d), mode="complete")
    return Q[:, d:]


def reference(name):
    pack = h5md.read_packing(f"{DATA}/{name}.h5")
    return case(pack), np.load(f"{DATA}/{name}.spectrum.npz")


# --- lowest modes ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["full", "relaxed"])
def test_lowest_20_equal_dense(jammed, dense_spectra, kind):
    s = jammed
    spec = spectrum.compute(WORLD, s.system, kind, k=20, method="sinvert")
    ref = dense_spectra[kind][s.d:s.d + 20]
    assert spec.complete and len(spec.eigenvalue) == 20
    assert np.all(np.abs(spec.eigenvalue / ref - 1) <= 1e-8)
    assert spec.error.max() <= spec.tolerance
    assert spec.n_unstable == 0 and not spec.unstable


@pytest.mark.parametrize("name", REFERENCE)
def test_lowest_20_equal_reference_spectra(name):
    """The independent implementation's dense spectra (translations kept there)."""
    s, ref = reference(name)
    for kind in ("full", "relaxed"):
        spec = spectrum.compute(WORLD, s.system, kind, k=20, method="sinvert")
        assert np.all(np.abs(spec.eigenvalue / ref[kind][s.d:s.d + 20] - 1) <= 1e-8)


@pytest.mark.parametrize("name", REFERENCE[1::2])
def test_dense_method_equals_reference_whole_spectrum(name):
    s, ref = reference(name)
    spec = spectrum.compute(WORLD, s.system, "full", k=s.n_modes, method="dense")
    assert len(spec.eigenvalue) == s.n_modes == len(ref["full"]) - s.d
    assert np.abs(spec.eigenvalue - ref["full"][s.d:]).max() <= 1e-13 * spec.norm


def test_deflation_removes_exactly_d_zero_modes(jammed, dense_spectra):
    s = jammed
    full = dense_spectra["full"]
    norm = np.abs(s.matrix("full")).sum(axis=1).max()
    zero_tol = spectrum.ZERO_TOL * norm
    # rattlers removed, periodic box: exactly the d translations are zero modes
    assert np.sum(np.abs(full) < zero_tol) == s.d
    deflated = spectrum.compute(WORLD, s.system, "full", k=s.n_modes, method="dense")
    assert np.allclose(deflated.eigenvalue, full[s.d:], rtol=0, atol=1e-13 * norm)
    spec = spectrum.compute(WORLD, s.system, "full", k=10, method="sinvert")
    assert spec.eigenvalue.min() > 1e3 * zero_tol  # no translation among the results
    assert np.allclose(spec.eigenvalue, full[s.d:s.d + 10], rtol=1e-9, atol=0)


# --- windows ---------------------------------------------------------------------------------
def window_between(eigs, lo_index, hi_index):
    """A frequency window whose ends lie half-way between neighbouring eigenvalues."""
    la = 0.5 * (eigs[lo_index - 1] + eigs[lo_index])
    lb = 0.5 * (eigs[hi_index] + eigs[hi_index + 1])
    return np.sqrt(la), np.sqrt(lb)


@pytest.mark.parametrize("kind", ["full", "relaxed"])
def test_slicing_count_equals_dense(jammed, dense_spectra, kind):
    s = jammed
    eigs = dense_spectra[kind]
    n10 = s.n_modes // 10
    for lo_index in (s.d, s.d + 7):  # from the bottom (window starting at 0) and inside
        wa, wb = window_between(eigs, lo_index, s.d + n10)
        if lo_index == s.d:
            wa = 0.0
        spec = spectrum.compute(WORLD, s.system, kind, window=(wa, wb), method="slice")
        inside = eigs[(eigs >= np.sign(wa) * wa**2 + 1e-9 * spec.norm * (wa == 0))
                      & (eigs <= wb**2)]
        assert spec.n_requested == len(inside)  # the inertia count
        assert spec.complete and len(spec.eigenvalue) == len(inside)
        assert np.allclose(spec.eigenvalue, inside, rtol=1e-7, atol=0)
        dense = spectrum.compute(WORLD, s.system, kind, window=(wa, wb), method="dense")
        assert len(dense.eigenvalue) == len(inside)
        if lo_index == s.d:  # below the window: the d translations only (a stable packing)
            assert spec.n_unstable == 0 and spec.info["below_window"] == s.d


def test_count_below_dense_is_sylvester_inertia(jammed, dense_spectra):
    s = jammed
    Q = deflation_basis(s.n, s.d)
    Hd = Q.T @ s.matrix("full") @ Q
    eigs = dense_spectra["full"][s.d:]
    for k in (0, 5, 40):
        sigma = 0.5 * (eigs[k] + eigs[k + 1])
        assert count_below_dense(Hd, sigma) == k + 1


# --- ranks, observables, vectors -------------------------------------------------------------
def test_one_rank_equals_all_ranks(jammed):
    s = jammed
    one = spectrum.compute(PETSc.COMM_SELF, s.on(PETSc.COMM_SELF), "full", k=15,
                           method="sinvert")
    many = spectrum.compute(WORLD, s.system, "full", k=15, method="sinvert")
    assert np.allclose(one.eigenvalue, many.eigenvalue, rtol=1e-11, atol=0)
    for key in ("participation_ratio", "eps_perp", "eps_par"):
        assert np.allclose(getattr(one, key), getattr(many, key), rtol=1e-7, atol=0)


@pytest.mark.parametrize("kind", ["full", "relaxed"])
def test_distributed_observables_equal_dense_vectors(jammed, kind):
    s = jammed
    sparse = spectrum.compute(WORLD, s.system, kind, k=12, method="sinvert", vectors=True)
    dense = spectrum.compute(WORLD, s.system, kind, k=12, method="dense", vectors=True)
    for key in ("participation_ratio", "eps_perp", "eps_par"):
        assert np.allclose(getattr(sparse, key), getattr(dense, key), rtol=1e-6, atol=0)
    for spec in (sparse, dense):  # each rank holds its own rows, tagged with particle ids
        assert spec.vectors.shape == (12, len(s.system.ids), s.d)
        assert np.array_equal(spec.vector_ids, s.system.ids)
    whole = [spectrum.vectors_on_root(WORLD, spec) for spec in (sparse, dense)]
    if WORLD.getRank() == 0:
        H = s.matrix(kind)  # rows in particle-id order, as vectors_on_root's
        for spec, vectors in zip((sparse, dense), whole):
            V = vectors.reshape(len(spec.eigenvalue), -1)
            assert vectors.shape == (12, s.n, s.d)
            res = np.linalg.norm(V @ H - V * spec.eigenvalue[:, None], axis=1)
            assert np.all(res <= 1e-9 * spec.norm)
            assert np.allclose(np.linalg.norm(V, axis=1), 1.0)
            assert np.allclose(observables.participation_ratio(vectors),
                               spec.participation_ratio, rtol=1e-8)
    else:
        assert whole == [None, None]


def test_relaxed_eigenvalue_is_twice_the_longitudinal_sum():
    """Monodisperse harmonic spheres: every stiffness V'' = 1, so for the relaxed matrix
    lambda = sum_<ij> [(dR_j - dR_i).n]^2 = 2 eps_par; the full matrix adds the (negative)
    transverse term."""
    s, _ = reference("ref_d3_mono_N128_dphi1e-03")
    spec = spectrum.compute(WORLD, s.system, "relaxed", k=30, method="sinvert")
    assert np.allclose(spec.eigenvalue, 2 * spec.eps_par, rtol=1e-9, atol=0)
    full = spectrum.compute(WORLD, s.system, "full", k=30, method="sinvert")
    assert np.all(full.eigenvalue < 2 * full.eps_par)


def test_stress_term_lowers_the_low_frequency_modes(jammed, dense_spectra):
    """Section IV: the stress term M' (negative) shifts the anomalous modes down, so below a
    small frequency D has more modes than M (at dphi = 1e-2)."""
    s = jammed
    omega = 0.15
    counts = {}
    for kind in ("full", "relaxed"):
        spec = spectrum.compute(WORLD, s.system, kind, window=(0.0, omega), method="slice")
        counts[kind] = len(spec.eigenvalue)
        assert counts[kind] == np.sum((dense_spectra[kind] > 1e-6) & (dense_spectra[kind]
                                                                      <= omega**2))
    assert counts["full"] > counts["relaxed"]


# --- D(omega) ----------------------------------------------------------------------------------
def test_dos_is_normalised_per_mode(jammed, dense_spectra):
    s = jammed
    w = observables.frequency(dense_spectra["full"][s.d:])
    edges = observables.dos_edges(w.max(), 30)
    centres, dos = observables.density_of_states(w, s.n_modes, edges)
    assert np.isclose(np.sum(dos * np.diff(edges)), 1.0, rtol=1e-12)
    # a partial spectrum gives the same D(omega) where it is complete
    part = w[:100]
    e2 = observables.dos_edges(part.max(), 10)
    _, d_part = observables.density_of_states(part, s.n_modes, e2)
    _, d_full = observables.density_of_states(w, s.n_modes, e2)
    assert np.allclose(d_part, d_full)


def test_plateau_and_omega_star_of_a_step():
    """D = D0 on [w*, 1]: the documented definitions return D0 and w* (to sampling accuracy)."""
    wstar, n = 0.2, 200_000
    w = np.linspace(wstar, 1.0, n)
    d0, ws, _ = observables.dos_summary(w, n)
    assert np.isclose(d0, 1.0 / (1.0 - wstar), rtol=1e-3)
    assert np.isclose(ws, wstar, rtol=1e-3)


def test_omega_star_falls_with_compression_direction(dense_spectra, jammed):
    """The relaxed matrix has fewer soft modes: its omega* is not below the full one's."""
    s = jammed
    stars = {}
    for kind in ("full", "relaxed"):
        w = observables.frequency(dense_spectra[kind][s.d:])
        stars[kind] = observables.dos_summary(w, s.n_modes)[1]
    assert 0 < stars["full"] <= stars["relaxed"]


# --- problems ----------------------------------------------------------------------------------
def test_unstable_packing_is_reported():
    """A random, unminimised overlapping configuration is no energy minimum: the full matrix has
    negative eigenvalues, found by the inertia of the shift-and-invert factor."""
    pack = random_packing(3, 64, 0.9, rng=np.random.default_rng(5))
    s = case(pack)
    dense = spectrum.compute(WORLD, s.system, "full", k=5, method="dense")
    sparse = spectrum.compute(WORLD, s.system, "full", k=5, method="sinvert")
    Q = deflation_basis(s.n, s.d)
    eigs = np.linalg.eigvalsh(Q.T @ s.matrix("full") @ Q)
    n_neg = int(np.sum(eigs < -spectrum.ZERO_TOL * dense.norm))
    assert n_neg > 0
    assert dense.unstable and sparse.unstable
    assert dense.n_negative == sparse.n_negative == n_neg


def test_unconverged_pairs_are_reported_not_kept(jammed):
    opts = PETSc.Options()
    opts.setValue("modes_eps_max_it", 1)
    opts.setValue("modes_eps_ncv", 12)
    try:
        spec = spectrum.compute(WORLD, jammed.system, "full", k=10, method="sinvert", tol=1e-14)
    finally:
        opts.delValue("modes_eps_max_it")
        opts.delValue("modes_eps_ncv")
    assert not spec.complete
    assert np.all(spec.error <= 1e-14)
    assert len(spec.eigenvalue) + len(spec.rejected_eigenvalue) <= 10


def test_bad_requests(jammed):
    s = jammed.system
    with pytest.raises(ParjamError, match="exceeds"):
        spectrum.compute(WORLD, s, "full", k=s.n_modes + 1)
    with pytest.raises(ParjamError, match="empty frequency window"):
        spectrum.compute(WORLD, s, "full", window=(0.5, 0.2))
    with pytest.raises(ParjamError, match="no nonzero mode"):
        spectrum.compute(WORLD, s, "full", window=(0.0, 1e-9), method="slice")
    with pytest.raises(ParjamError, match="spans the d translations"):
        spectrum.compute(WORLD, s, "full", window=(-0.1, 0.1), method="slice")
    with pytest.raises(ParjamError, match="holds no eigenvalue"):
        spectrum.compute(WORLD, s, "full", window=(1e-3, 2e-3), method="slice")
    with pytest.raises(ParjamError, match="holds no eigenvalue"):
        spectrum.compute(WORLD, s, "full", window=(1e-3, 2e-3), method="dense")


def test_unjammed_and_contactless_packings():
    dilute = random_packing(3, 64, 0.05, rng=np.random.default_rng(1))
    with pytest.raises(UnjammedError, match="unjammed"):
        dense_system(dilute)
    with pytest.raises(UnjammedError, match="unjammed"):
        spectrum.system_of(WORLD, dilute)
    g = np.arange(4) + 0.5
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) * 1.5
    apart = Packing(lattice, np.ones(64), 6.0)
    assert len(network.find_contacts(apart)) == 0
    with pytest.raises(ParjamError, match="no contacts"):
        dense_system(apart)
    with pytest.raises(ParjamError, match="no contacts"):
        spectrum.system_of(WORLD, apart)


def test_stress_term_alone_is_negative_semidefinite(jammed):
    """M' has only eigenvalues <= 0: a window on the negative side finds them all, and the
    sinvert modes nearest zero are all negative; no instability is claimed for M'."""
    s = jammed
    eigs = np.linalg.eigvalsh(s.matrix("stress"))
    norm = np.abs(s.matrix("stress")).sum(axis=1).max()
    assert eigs.max() <= 1e-12 * norm
    neg = eigs[eigs < -1e-6]  # the 12 negative eigenvalues nearest zero
    wa = -np.sqrt(-0.5 * (neg[-13] + neg[-12]))
    spec = spectrum.compute(WORLD, s.system, "stress", window=(wa, -1e-3), method="slice")
    expect = neg[-12:]
    assert len(spec.eigenvalue) == len(expect) and np.allclose(spec.eigenvalue, expect, rtol=1e-7)
    assert not spec.unstable


def test_auto_method_choice():
    assert spectrum.choose_method("auto", 3000, None) == "dense"
    assert spectrum.choose_method("auto", 3001, None) == "sinvert"
    assert spectrum.choose_method("auto", 3001, (0.0, 0.1)) == "slice"
    assert spectrum.choose_method("auto", 3001, (0.0, 0.1), k=5, n_modes=2998) == "slice"
    # the k lowest modes between SMALL_DOF and PARTIAL_DENSE_MAX_DOF (docs/results/speed-accuracy.md)
    assert spectrum.choose_method("auto", 1000, None, k=10, n_modes=997) == "sinvert"
    assert spectrum.choose_method("auto", 1000, None, k=150, n_modes=997) == "dense"
    assert spectrum.choose_method("auto", 1000, None, k=10, n_modes=997, tol=1e-13) == "dense"
    assert spectrum.choose_method("auto", 400, None, k=1, n_modes=397) == "dense"
    assert spectrum.choose_method("sinvert", 100, None, k=1, n_modes=97) == "sinvert"


def test_solver_policy_whole_spectrum_and_limits():
    """The one policy (parjam.vib.solver_choice) of modes, scenes and lengths: whole spectra by dense
    up to WHOLE_MAX_DOF, then KPM when D(omega) alone is wanted, else a one-line error; a
    window and k together beyond dense by slicing and shift-and-invert; moved limits obeyed."""
    choose = solver_choice.choose_solver
    big = solver_choice.WHOLE_MAX_DOF
    assert choose(big, big - 3, whole=True) == "dense"
    assert choose(big + 1, big - 2, whole=True, dos_only=True) == "kpm"
    with pytest.raises(ParjamError, match="beyond dense"):
        choose(big + 1, big - 2, whole=True)
    assert choose(5000, 4997, k=10, window=(0.0, 0.1)) == "slice+sinvert"
    no_dense = solver_choice.Limits(partial_dense_max_dof=0)
    assert choose(192, 189, k=5, limits=no_dense) == "sinvert"
    assert choose(192, 189, window=(0.0, 0.3), limits=no_dense) == "slice"
    with pytest.raises(ParjamError):
        choose(1200, 1197, whole=True, limits=solver_choice.Limits(whole_max_dof=1000))


def test_matrices_are_the_three_terms_of_eq_1(jammed):
    """Every name in MATRICES is a matrix of Eq. (1) that the commands offer, and the full one
    is the sum of the other two, D = M + M'."""
    assert set(spectrum.MATRICES) == {"full", "relaxed", "stress"}
    full, relaxed, stress = (jammed.matrix(kind) for kind in
                             ("full", "relaxed", "stress"))
    np.testing.assert_allclose(full, relaxed + stress, atol=1e-13 * np.abs(full).max())
    assert np.abs(stress).max() > 1e-8 * np.abs(relaxed).max()  # the sum is not trivial
    parser = cli.build_parser()
    for command, required in (("modes", ["--k", "5"]), ("dos", [])):
        argv = [command, "F.h5", "--out", "o.h5", *required, "--matrix"]
        for kind in spectrum.MATRICES:  # each is accepted, one more name is refused
            assert parser.parse_args(argv + [kind]).matrix in (kind, [kind])
        with pytest.raises(SystemExit):
            parser.parse_args(argv + ["hessian"])
