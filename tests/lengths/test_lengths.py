"""Sound speeds, the lengths l_L, l_T, l* and the structure factors of the eigenmodes
(parjam.lengths, parjam.vib.structure).  Runs serially and under ``mpirun -n 2``."""

import os
from types import SimpleNamespace

import numpy as np
import pytest

from parjam import cli, env, lengths
from parjam.files import h5md
from parjam.vib import moduli, structure
from parjam.errors import ParjamError
from conftest import DATA

SELF = env.petsc().COMM_SELF


def data(name):
    return h5md.read_packing(os.path.join(DATA, name))


@pytest.fixture(scope="module")
def compressed(world):
    """2D bidisperse N = 1024 at dphi = 1e-1: speeds and structure factors (complete dense
    spectrum of the full matrix, wavevectors up to k = 1.8)."""
    pack = data("lengths_d2_N1024_dphi1e-01.h5")
    return pack, lengths.compute(world, pack, ("speeds", "structure"), k_max=1.8)


# --- sound speeds -----------------------------------------------------------------------------
@pytest.mark.parametrize("d", [2, 3])
def test_christoffel_of_isotropic_prestressed_solid(d):
    """For isotropic Lagrangian constants (lambda', mu') under pressure p, the waves of the
    pre-stressed solid travel at c_T = sqrt(G/rho), c_L = sqrt((B + 2(d-1)G/d)/rho) with the
    stress-strain (Wallace) B and G: the density and pre-stress conventions agree."""
    lam, mu, p, rho = 0.7, 0.3, 0.05, 1.3
    e = np.eye(d)
    C = (lam * np.einsum("ij,kl->ijkl", e, e)
         + mu * (np.einsum("ik,jl->ijkl", e, e) + np.einsum("il,jk->ijkl", e, e)))
    s = -p * e
    Bt = moduli.stress_strain_tensor(C, s)
    B, G = moduli.bulk_modulus(Bt), moduli.shear_modulus(Bt)
    assert G == pytest.approx(mu - p) and B == pytest.approx(lam + 2 * mu / d + p - 2 * p / d)
    c_L, c_T = lengths.sound_speeds(B, G, d, rho)
    khat = np.random.default_rng(0).normal(size=(5, d))
    khat /= np.linalg.norm(khat, axis=1)[:, None]
    mod = SimpleNamespace(d=d, c_lagrangian=C, stress=s)
    c = lengths.christoffel_speeds(mod, khat, rho)
    np.testing.assert_allclose(c[:, :-1], c_T, rtol=1e-12)
    np.testing.assert_allclose(c[:, -1], c_L, rtol=1e-12)


def test_density_is_that_of_the_non_rattlers(compressed):
    pack, res = compressed
    assert res.rho == pytest.approx(res.n_active / pack.volume)
    assert res.n_active < pack.n  # this packing has a rattler: rho != N / V


# --- structure factors ------------------------------------------------------------------------
def test_amplitudes_against_explicit_sum():
    rng = np.random.default_rng(1)
    pos, vec = rng.uniform(0, 5, (7, 3)), rng.normal(size=(4, 7, 3))
    kv = 2 * np.pi * structure.wavevector_indices(5.0, 3, 3.0) / 5.0
    A = structure.mode_amplitudes(vec, pos, kv)
    ref = np.einsum("mia,ki->kma", vec, np.exp(1j * pos @ kv.T).T)
    np.testing.assert_allclose(A, ref, atol=1e-12)
    m = structure.wavevector_indices(5.0, 3, 3.0)
    assert len(np.unique(m, axis=0)) == len(m) and not any((-r == m).all(1).any() for r in m)


def test_weights_sum_rule(compressed):
    """Over a complete set of modes the weights of one k sum to 1 - |rho_k|^2 / N'^2 per
    polarisation (the translations take the rest): checks amplitudes and normalisation."""
    pack, res = compressed
    sf = res.structure
    assert len(sf.omega) == 2 * res.n_active - 2
    from parjam.net.network import analyze

    pos = pack.pos[~analyze(pack).rattler]
    m = structure.wavevector_indices(pack.L, 2, 1.8)
    kv = 2 * np.pi * m / pack.L
    rho_k2 = np.abs(np.exp(1j * pos @ kv.T).sum(axis=0)) ** 2 / len(pos) ** 2
    m2 = (m * m).sum(axis=1)
    expect = np.array([1 - rho_k2[m2 == s].mean() for s in sf.m2])
    np.testing.assert_allclose(sf.weight_L.sum(axis=1), expect, atol=1e-9)
    np.testing.assert_allclose(sf.weight_T.sum(axis=1), expect, atol=1e-9)


def test_dispersion_slopes_match_moduli(compressed):
    """dphi = 1e-1: the peaks of F_T and F_L at the smallest wavevectors follow omega = c k with
    c from the moduli by linear response (measured: -3 % and +2 % on this packing; 10 %
    allowed).  The box is large against l* (k_min l* ~ 0.5), so the finite-k stiffening is small."""
    _, res = compressed
    c_L, c_T = res.speeds
    fit = res.structure_fit
    assert fit["c_T_fit"] == pytest.approx(c_T, rel=0.10)
    assert fit["c_L_fit"] == pytest.approx(c_L, rel=0.10)
    # the branches are distinct: transverse below longitudinal at every shell
    assert np.all(fit["peak_T"] < fit["peak_L"])
    # l_T from the structure factor: 1/k where the transverse peak reaches omega*, within 30 %
    # of c_T / omega* (the dispersion is not linear up to omega*)
    assert fit["l_T_structure"] == pytest.approx(res.acoustic[1] if res.acoustic else
                                                 c_T / res.omega_star, rel=0.3)


def test_peak_of_a_single_mode():
    w = np.array([0.0, 0.0, 1.0, 0.0])
    assert structure.peak_frequency(np.array([0.1, 0.2, 0.3, 0.4]), w) == pytest.approx(
        0.3, rel=1e-3)


# --- l* ---------------------------------------------------------------------------------------
def test_lstar_counts_and_scaling(world):
    """Cut cubes in 2D N = 1024 at dphi = 1e-1 and 1e-3: the measured l* (cut-plane count of
    the real cubes changes sign) is within a factor of ~2 of the Maxwell estimate d z <|r_a|>/dz
    and grows as dz falls, and so does the size at which extended soft modes disappear; every
    exact soft-mode count is >= the Maxwell bound of its core and >= its extended count; the
    counts on COMM_SELF and on all ranks agree."""
    out = {}
    for name in ("1e-01", "1e-03"):
        pack = data(f"lengths_d2_N1024_dphi{name}.h5")
        ells = np.geomspace(2.0, 0.7 * pack.L, 9)
        res = lengths.lstar(world, pack, ells, samples=4, seed=1)
        ref = lengths.lstar(SELF, pack, ells, samples=4, seed=1)
        np.testing.assert_array_equal(res.table(), ref.table())
        assert [c.extended for c in res.counts] == [c.extended for c in ref.counts]
        for c in res.counts:
            if c.null >= 0:
                assert c.soft >= c.maxwell_core
            if c.extended >= 0:
                assert c.extended <= c.soft
            assert c.maxwell == 2 * c.n - c.nc_in - 3
        assert 0.4 < res.measured / res.estimate < 1.5, (res.measured, res.estimate)
        out[name] = res
    # extended soft modes disappear at a size of the order of the estimate as well (at
    # dphi = 1e-3 they are still there in the largest cubes tried: NaN, beyond the range)
    ext = out["1e-01"].extended_measured
    assert 0.5 < ext / out["1e-01"].estimate < 3.0, (ext, out["1e-01"].estimate)
    t = out["1e-03"].table()
    assert np.isnan(out["1e-03"].extended_measured) or out["1e-03"].extended_measured > 2 * ext
    assert np.nanmax(t[t[:, 0] > 2 * ext, 9]) > 0.25  # extended soft modes in larger cubes
    grow = out["1e-03"].measured / out["1e-01"].measured
    shrink = out["1e-03"].dz / out["1e-01"].dz
    assert grow > 0.5 / shrink, (grow, shrink)


# --- 1 rank vs 2 ranks, CLI, bad input ---------------------------------------------------------
def test_one_vs_all_ranks(world):
    pack = data("ref_d3_mono_N128_dphi1e-03.h5")
    a = lengths.compute(SELF, pack, ("speeds", "omega")).summary()
    b = lengths.compute(world, pack, ("speeds", "omega")).summary()
    for key in ("c_L", "c_T", "omega_star", "l_L", "l_T", "rho"):
        assert a[key] == pytest.approx(b[key], rel=1e-8), key


def test_cli_output_and_bad_input(shared_tmp, world, capsys):
    import h5py

    src = os.path.join(DATA, "ref_d2_bi_N128_dphi1e-03.h5")
    out = os.path.join(shared_tmp, "len.h5")
    code = cli.main(["lengths", src, "--what", "speeds", "omega", "lstar", "--samples", "2",
                     "--edges", "0.3,0.6,1", "--out", out, "-q"])
    assert code == 0
    ref = lengths.compute(SELF, h5md.read_packing(src), ("speeds", "omega"))
    with h5py.File(out, "r") as f:
        g = f["lengths"]
        assert g.attrs["c_T"] == pytest.approx(ref.speeds[1], rel=1e-8)
        assert g.attrs["l_L"] == pytest.approx(ref.acoustic[0], rel=1e-8)
        assert g["lstar/cubes"].shape == (6, 13)
        assert "structure" not in g  # only what was asked for
    if world.getRank() == 0:
        assert "c_L, c_T" in capsys.readouterr().out
    # bad input: a loose packing, an unknown quantity, an edge outside (0, 1]
    pack = h5md.read_packing(src)
    loose = pack.rescaled(pack.phi - 0.05)
    with pytest.raises(ParjamError, match="not jammed"):
        lengths.compute(world, loose, ("speeds",))
    bad = os.path.join(shared_tmp, "loose.h5")
    if world.getRank() == 0:
        from parjam.net.network import analyze

        h5md.write_packing(bad, loose, analyze(loose), {})
    world.tompi4py().Barrier()
    no = os.path.join(shared_tmp, "no.h5")
    assert cli.main(["lengths", bad, "--out", no, "-q"]) == 2
    assert cli.main(["lengths", src, "--what", "sound", "-q"]) == 2
    assert cli.main(["lengths", src, "--what", "lstar", "--edges", "0,1.5", "-q"]) == 2
    assert not os.path.exists(no)
    err = capsys.readouterr().err
    if world.getRank() == 0:
        assert "not jammed" in err and "--what sound" in err and "--edges" in err
