"""Jammed packings: force balance, isostaticity at phi_c, the scaling laws p ~ dphi and
dZ ~ dphi^(1/2) (O'Hern et al. 2003), the phi_c values, pressure targets and determinism.

The ensembles are made once per session through the real command (``parjam pack``), with the
members spread over the ranks of the MPI pass.
"""

import glob
import os

import h5py
import numpy as np
import pytest

from parjam import cli, env
from parjam.files.h5md import observable, read_packing
from parjam.net.network import analyze

MEMBERS = 10
DPHIS_3D = [1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1]
DPHIS_2D = [1e-8, 1e-6, 1e-1]


def _make(tmp, name, argv):
    out = os.path.join(tmp, name)
    assert cli.main(["pack", *argv, "--members", str(MEMBERS), "--out", out, "-q"]) == 0
    states = {}
    for path in sorted(glob.glob(os.path.join(out, "*.h5"))):
        with h5py.File(path, "r") as f:
            params = dict(f["parameters"].attrs)
        net = analyze(read_packing(path))
        states.setdefault(str(params["state"]), []).append((params, net))
    return states


@pytest.fixture(scope="session")
def ensemble3d(shared_tmp):
    return _make(shared_tmp, "e3d", ["--dim", "3", "--n", "256", "--seed", "11",
                                     "--dphi", *map(str, DPHIS_3D)])


@pytest.fixture(scope="session")
def ensemble2d(shared_tmp):
    return _make(shared_tmp, "e2d", ["--dim", "2", "--n", "256", "--dispersity", "bi",
                                     "--seed", "12", "--dphi", *map(str, DPHIS_2D)])


def _label(dphi):
    return f"dphi{dphi:.1e}"


@pytest.mark.parametrize("which", ["ensemble3d", "ensemble2d"])
def test_force_balance_at_extremes(which, request):
    ens = request.getfixturevalue(which)
    for label in ("phi_c", _label(1e-8), _label(1e-1)):
        assert len(ens[label]) == MEMBERS
        for params, net in ens[label]:
            assert net.max_force <= 1e-13, (label, params["member"], net.max_force)
            assert params["minimiser_status"] == "converged"


@pytest.mark.parametrize("which", ["ensemble3d", "ensemble2d"])
def test_isostatic_at_jamming(which, request):
    ens = request.getfixturevalue(which)
    excess = np.array([net.excess for _, net in ens["phi_c"]])
    assert np.all(excess >= 0), excess  # a jammed packing is never hypostatic
    assert np.mean(excess == 0) >= 0.9, excess
    near = np.array([net.excess for _, net in ens[_label(1e-6)]])
    assert np.all((near >= 0) & (near <= 4)), near


def _slope(x, y):
    return np.polyfit(np.log(x), np.log(y), 1)[0]


def test_pressure_linear_in_dphi(ensemble3d):
    dphis = [d for d in DPHIS_3D if 1e-6 <= d <= 1e-2]
    p = [np.mean([net.pressure for _, net in ensemble3d[_label(d)]]) for d in dphis]
    assert _slope(dphis, p) == pytest.approx(1.0, abs=0.1)


def test_excess_coordination_sqrt_dphi(ensemble3d):
    dphis = [d for d in DPHIS_3D if 1e-4 <= d <= 1e-1]
    dz = [np.mean([2.0 * net.excess / net.n_active for _, net in ensemble3d[_label(d)]])
          for d in dphis]
    assert 0.4 <= _slope(dphis, dz) <= 0.65, dz


def test_phi_c_values(ensemble3d, ensemble2d):
    phi3 = np.mean([p["phi_c"] for p, _ in ensemble3d["phi_c"]])
    phi2 = np.mean([p["phi_c"] for p, _ in ensemble2d["phi_c"]])
    assert 0.63 <= phi3 <= 0.65
    assert 0.83 <= phi2 <= 0.85


def test_states_record_protocol(ensemble3d):
    params, net = ensemble3d[_label(1e-2)][0]
    assert params["protocol"] == "ohern-bisection+ladder"
    assert params["ladder"] == "compress"
    assert params["phi"] == pytest.approx(params["phi_c"] + 1e-2, abs=1e-12)
    lo, hi = params["energy_window"]
    for p, n in ensemble3d["phi_c"]:
        e = n.energy / n.n
        assert lo <= e <= hi


def test_decompression_ladder_and_pressure_targets(shared_tmp):
    out = os.path.join(shared_tmp, "dec")
    assert cli.main(["pack", "--dim", "2", "--n", "64", "--dispersity", "bi", "--seed", "3",
                     "--dphi", "1e-3", "1e-5", "--ladder", "decompress", "--out", out,
                     "-q"]) == 0
    with h5py.File(os.path.join(out, "member0000_dphi1.0e-05.h5")) as f:
        assert f["parameters"].attrs["ladder"] == "decompress"
        assert observable(f, "max_force") <= 1e-13
    outp = os.path.join(shared_tmp, "press")
    assert cli.main(["pack", "--dim", "3", "--n", "64", "--seed", "3", "--pressure", "1e-3",
                     "1e-5", "--alpha", "2.5", "--out", outp, "-q"]) == 0
    for p in (1e-3, 1e-5):
        net = analyze(read_packing(os.path.join(outp, f"member0000_p{p:.1e}.h5")))
        assert net.pressure == pytest.approx(p, rel=1e-6)
        assert net.max_force <= 1e-13


def test_distributed_minimisation_matches_serial(world):
    """One packing minimised across all ranks equals the serial one bitwise: a quench at fixed
    phi (FIRE, Newton and the stability check) and the phi_c of the bisection and its
    refinement (tests/pack/test_rank_independence.py: the files of whole protocols)."""
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, make_jammed, random_packing

    PETSc = env.petsc()
    states = []
    for comm in (PETSc.COMM_SELF, world):
        jam = Jammer(comm, random_packing(3, 128, 0.70, 2.0, "mono", 1.4, member_rng(5, 0)))
        states.append(jam.at_phi(0.70, "q").pack)
        jam.destroy()
    p_s, p_w = states
    assert np.array_equal(p_w.pos, p_s.pos) and p_w.L == p_s.L
    n_s, n_w = analyze(p_s), analyze(p_w)
    assert n_s.n_contacts == n_w.n_contacts and n_w.pressure == n_s.pressure
    assert n_w.max_force <= 1e-13
    phi_s, _ = make_jammed(3, 128, [], seed=5, comm=PETSc.COMM_SELF)
    phi_w, _ = make_jammed(3, 128, [], seed=5, comm=world)
    assert phi_w == phi_s


@pytest.mark.parametrize("d", [2, 3])
def test_extrapolated_phi_c_matches_bisection_of_same_configuration(d):
    """The decompression protocol (--phic-method extrapolate) estimates phi_c from the virial
    relation phi - phi_c = alpha E phi / (p V); the O'Hern bisection continued from the state it
    reaches (the same configuration) must agree to a few percent of dphi.  Measured at N = 256,
    3D: 1-2 % at dphi = 1e-3, below 0.6 % at 1e-4 and 1e-5.  (Serial on each rank: the
    distributed minimiser is compared with the serial one above.)"""
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    phi0 = {2: 0.86, 3: 0.66}[d]
    pack = random_packing(d, 128, phi0, 2.0, "mono" if d == 3 else "bi", 1.4, member_rng(7, 0))
    jam = Jammer(env.petsc().COMM_SELF, pack)
    try:
        st = jam.find_phi_c_from_above(1e-4)
        assert 1e-4 / 1.5 <= st.info["dphi_est"] <= 1.5e-4
        assert st.result.fmax <= 1e-13
        ref = jam.find_phi_c().info["phi_c"]
    finally:
        jam.destroy()
    assert abs(st.info["phi_c"] - ref) <= 0.03 * st.info["dphi_est"]


def test_pack_cli_extrapolate_writes_ladder_without_phi_c_file(shared_tmp):
    out = os.path.join(shared_tmp, "extrap")
    assert cli.main(["pack", "--dim", "3", "--n", "128", "--seed", "4", "--dphi", "1e-3", "1e-2",
                     "--phic-method", "extrapolate", "--out", out, "-q"]) == 0
    names = sorted(os.path.basename(p) for p in glob.glob(os.path.join(out, "*.h5")))
    assert names == ["member0000_dphi1.0e-02.h5", "member0000_dphi1.0e-03.h5"]
    nets = []
    for name in names:
        with h5py.File(os.path.join(out, name)) as f:
            assert f["parameters"].attrs["protocol"] == "virial-extrapolation+ladder"
        nets.append(analyze(read_packing(os.path.join(out, name))))
    # p ~ dphi near jamming (harmonic): a wrong phi_c would bend the ratio far from 10
    assert nets[0].pressure / nets[1].pressure == pytest.approx(10.0, rel=0.15)
    assert max(n.max_force for n in nets) <= 1e-13
    bad = cli.main(["pack", "--dim", "3", "--n", "64", "--phi", "0.7", "--phic-method",
                    "extrapolate", "--out", os.path.join(shared_tmp, "extrap-bad"), "-q"])
    assert bad != 0


def test_newton_with_cg_gamg_reaches_the_same_minimum():
    """-newton_ksp_type cg -newton_pc_type gamg (no factorisation, for very large N) converges
    to the same minimum as the default MUMPS LDL^T from the same FIRE hand-over."""
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    PETSc = env.petsc()
    opts = PETSc.Options()
    out = []
    for cg in (False, True):
        if cg:
            opts["newton_ksp_type"] = "cg"
            opts["newton_pc_type"] = "gamg"
            opts["newton_ksp_rtol"] = 1e-10
        try:
            jam = Jammer(PETSc.COMM_SELF, random_packing(3, 256, 0.70, 2.0, "mono", 1.4,
                                                         member_rng(9, 0)))
            st = jam.at_phi(0.70, "q")
            assert jam.ff.newton_ksp.ksp_type == ("cg" if cg else "preonly")
            out.append((st.pack, st.result, jam.total_newton))
            jam.destroy()
        finally:
            for key in ("newton_ksp_type", "newton_pc_type", "newton_ksp_rtol"):
                opts.delValue(key)
    (p0, r0, n0), (p1, r1, n1) = out
    assert r0.fmax <= 1e-13 and r1.fmax <= 1e-13
    assert n0 > 0 and n1 > 0  # Newton did run in both
    d = p1.pos - p0.pos
    d -= p0.L * np.rint(d / p0.L)
    assert np.abs(d).max() < 1e-8


def test_fire_to_the_tolerance_reaches_the_newton_minimum(monkeypatch):
    """Above minimize.FIRE_TAIL_DOF FIRE converges to ftol by itself (no Newton step): from the
    same start it ends in the minimum that FIRE + Newton finds, and that minimum is stable (its
    dense Hessian has no negative eigenvalue beyond round-off)."""
    from parjam.pack import minimize
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    PETSc = env.petsc()
    out = []
    for tail_dof in (10**9, 0):  # FIRE + Newton (default at this size), then FIRE alone
        monkeypatch.setattr(minimize, "FIRE_TAIL_DOF", tail_dof)
        jam = Jammer(PETSc.COMM_SELF, random_packing(3, 256, 0.70, 2.0, "mono", 1.4,
                                                     member_rng(9, 0)))
        st = jam.at_phi(0.70, "q")
        H = jam.ff.hessian().convert("dense").getDenseArray().copy()
        out.append((st.pack, st.result, jam.total_newton, H))
        jam.destroy()
    (p0, r0, n0, _), (p1, r1, n1, H1) = out
    assert r0.fmax <= 1e-13 and r1.fmax <= 1e-13
    assert n0 > 0 and n1 == 0
    assert r1.energy == pytest.approx(r0.energy, rel=1e-12)
    d = p1.pos - p0.pos
    d -= p0.L * np.rint(d / p0.L)
    d -= d.mean(axis=0)  # the minimum is defined up to a global translation
    assert np.abs(d).max() < 1e-9
    lam = np.linalg.eigvalsh(0.5 * (H1 + H1.T))
    assert lam[0] > -1e-10 * lam[-1]


def test_random_start_numbers_neighbours_nearby():
    """Particles are numbered cell by cell (parjam.pack.packing.spatial_order): the index distance
    of neighbour pairs is small against N (random numbering: ~N/3), every cell's particles are
    contiguous, and bidisperse species stay mixed in space."""
    from parjam.pack.packing import member_rng
    from parjam.net.system import neighbour_pairs
    from parjam.pack.packing import random_packing

    pack = random_packing(3, 8000, 0.66, 2.0, "bi", 1.4, member_rng(3, 0))
    pairs = neighbour_pairs(pack.pos, pack.L, 1.4)
    gap = np.abs(pairs[:, 0] - pairs[:, 1])
    assert np.median(gap) < 0.05 * pack.n
    species = pack.meta["species"]
    assert species.sum() == pack.n // 2
    half = pack.pos[:, 0] < 0.5 * pack.L  # each half-box holds both species in equal parts
    assert abs(species[half].mean() - 0.5) < 0.05
