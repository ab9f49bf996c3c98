"""Honest at the extremes: phi_c refined from the jammed side so that p / dphi is
constant down to dphi = 1e-9; every returned state a stable minimum (a constructed saddle is
detected, against a dense eigenvalue count, and relaxed to a stable minimum, by the escapes
or, with those switched off, by the compression cycle, which a checkpointed resume repeats); a
state that cannot be stabilised is flagged, not dropped; a state whose own virial dphi
disagrees with its label is flagged; a ladder step that unjams keeps the states before it
(written, exit 3); tolerances that cannot define a jammed state are refused.

The ladders are built on COMM_SELF (every rank of the MPI pass builds the same ones: a member
shared by 2 ranks costs 30x more FIRE time on this loaded machine); the stability checks and the
escape from the saddle run on COMM_WORLD (the MUMPS inertia and SLEPc on two ranks)."""

import os

import h5py
import numpy as np
import pytest

from parjam.net.blocks import contact_blocks
from parjam import env
from parjam.files import h5md
from parjam.net import network
from parjam.pack import jamnet, packing, stability
from parjam.vib import hessian
from parjam.errors import ParjamError
from parjam.pack.minimize import MinResult
from parjam.pack.packing import Jammer, make_jammed
from parjam.pack.protocol import check_tolerances
from parjam.testing import saddles

PETSc = env.petsc()
DPHIS = [1e-9, 1e-8, 1e-7, 1e-6]


@pytest.fixture(scope="module", params=[3, 2], ids=["3d-mono", "2d-bi"])
def ladder(request):
    d = request.param
    return d, make_jammed(d, 64, DPHIS, seed=4, comm=PETSc.COMM_SELF)


def test_pressure_proportional_to_dphi(ladder):
    """Harmonic: p = c dphi near jamming.  With the bisection's phi_c alone (E/N ~ 1.5e-16, i.e.
    ~2.5e-8 above the true phi_c) p / dphi at 1e-9 was ~10x its 1e-6 value; refined, it agrees
    to < 2 % over three decades (and the virial dphi of each state matches its label)."""
    d, (phi_c, packs) = ladder
    ratio = []
    for dphi, pack in zip(DPHIS, packs):
        net = network.analyze(pack)
        assert net.excess >= 0 and pack.meta["stable"] == 1
        assert pack.meta["dphi_virial"] == pytest.approx(dphi, rel=0.02)
        ratio.append(net.pressure / dphi)
    ratio = np.array(ratio)
    assert np.all(np.abs(ratio / ratio[-1] - 1.0) < 0.02), ratio
    slope = np.polyfit(np.log(DPHIS), np.log(ratio * DPHIS), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.01)


def dense_active_hessian(pack):
    """The serial dense D of the non-rattlers (active numbers in particle order) and their
    particle indices: the reference of the distributed stability check."""
    net = network.analyze(pack)
    c = network.active_contacts(net)
    blocks = contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    n = net.n_active
    return hessian.dense_hessian(n, pack.d, c.i, c.j, blocks), np.flatnonzero(~net.rattler)


def _dense_negatives(pack, shift):
    D, _ = dense_active_hessian(pack)
    return int(np.sum(np.linalg.eigvalsh(D) < -shift))


def test_saddle_detected_and_relaxed(ladder, world):
    d, (phi_c, packs) = ladder
    stable = packs[1]  # dphi = 1e-8
    s0 = stability.check(world, jamnet.from_packing(world, stable))
    assert s0.stable and s0.n_negative == _dense_negatives(stable, s0.shift) == 0
    saddle = saddles.along_soft_mode(stable, opened=2)
    net = network.analyze(saddle)
    assert net.excess < 0
    cur = stability.check(world, jamnet.from_packing(world, saddle))
    assert not cur.stable
    dense = _dense_negatives(saddle, cur.shift)
    assert dense >= 1
    if cur.method == "lanczos":  # it certifies a negative curvature and counts those it found
        assert 1 <= cur.n_negative <= dense
    else:
        assert cur.n_negative == dense  # MUMPS inertia vs LAPACK
    jam = Jammer(PETSc.COMM_SELF, saddle)  # (a shared FIRE run costs minutes in the MPI pass)
    try:
        res, info = jam.stabilise(MinResult("converged", 0.0, 0.0))
        final = jam.packing_for_file()
    finally:
        jam.destroy()
    after = network.analyze(final)
    assert info["stable"] == 1 and info["escapes"] >= 0
    assert after.excess >= 0 and after.max_force < 1e-13
    assert _dense_negatives(final, info["curvature_shift"]) == 0
    assert after.pressure == pytest.approx(network.analyze(stable).pressure, rel=0.05)


def test_unstabilisable_state_is_flagged_not_dropped(ladder, world, monkeypatch):
    """With no escape and no compression cycle allowed, the saddle comes back flagged
    (stable = 0)."""
    d, (phi_c, packs) = ladder
    saddle = saddles.along_soft_mode(packs[1], opened=2)
    monkeypatch.setattr(packing, "MAX_ESCAPES", 0)
    monkeypatch.setattr(packing, "CYCLE_FACTORS", ())
    jam = Jammer(world, saddle)  # no minimisation: the checks only, on every rank
    try:
        st = jam.stable_state(MinResult("converged", 0.0, 0.0), "saddle")
    finally:
        jam.destroy()
    assert st.info["stable"] == 0 and st.info["escapes"] == 0 and st.info["cycles"] == 0
    assert st.info["negative_curvatures"] >= 1 and st.info["excess_found"] < 0


@pytest.mark.serial
def test_flagged_member_written_and_counted(tmp_path, monkeypatch, capsys):
    """pack_member with the stabilisation failing for one state: every file is written, the
    failing one with /observables/stable = 0, and the ensemble's summary line counts it."""
    from parjam.study import members
    from parjam.progress import Progress
    from parjam.pack.protocol import PackingProtocol

    real = Jammer.stabilise

    def failing(self, res, *a):
        res, info = real(self, res, *a)
        if abs(self.pack.phi - getattr(self, "_phi_c_test", 0.0)) < 2e-6:
            info["stable"] = 0
        return res, info

    monkeypatch.setattr(Jammer, "stabilise", failing)
    args = PackingProtocol(dim=3, n=32, out=str(tmp_path), seed=1, dphi=(1e-6, 1e-3),
                           resume=False)
    refine = Jammer.refine_phi_c

    def remember(self, dphi_stop, *a, **k):
        out = refine(self, dphi_stop, *a, **k)
        self._phi_c_test = out["phi_c"]
        return out

    monkeypatch.setattr(Jammer, "refine_phi_c", remember)
    rows = members.pack_member(args, 0, PETSc.COMM_SELF, Progress(PETSc.COMM_WORLD, True))
    assert {r["state"] for r in rows} == {"phi_c", "dphi1.0e-06", "dphi1.0e-03"}
    flags = {}
    for r in rows:
        with h5py.File(r["file"], "r") as f:
            flags[r["state"]] = int(h5md.observable(f, "stable"))
    assert flags["dphi1.0e-06"] == 0 and flags["dphi1.0e-03"] == 1
    line = members.stability_line(rows)
    assert "1 of 3 states" in line and "dphi1.0e-06" in line
    back = members.rows_from_files(str(tmp_path), 0,
                                    [os.path.basename(r["file"]) for r in rows])
    assert sorted(r["stable"] for r in back) == [0, 1, 1]


@pytest.mark.parametrize("ftol,window,why", [
    (1e-13, (1e-30, 2e-30), "round-off of 1 - r/sigma"),
    (1e-13, (1e-16, 1.01e-16), "too narrow"),
    (1e-13, (1e-16, 1e-2), "not near jamming"),
    (1e-8, (1e-16, 2e-16), "not small against the contact forces"),
    (1e-19, (1e-16, 2e-16), "below the round-off level"),
])
def test_tolerances_refused(ftol, window, why):
    with pytest.raises(ParjamError, match=why):
        check_tolerances(ftol, window, 2.0, 3)


def test_default_tolerances_accepted():
    for alpha in (1.5, 2.0, 2.5, 3.0):  # alpha < 2: no round-off floor is checked
        for d in (2, 3):
            check_tolerances(1e-13, (1e-16, 2e-16), alpha, d)


@pytest.mark.serial
def test_energy_window_cli_refused(tmp_path):
    """The issue's example: exit 2 and one line before any work, no file."""
    import subprocess
    import sys

    from conftest import subprocess_env

    out = tmp_path / "p"
    r = subprocess.run([sys.executable, "-m", "parjam", "pack", "--n", "64", "--energy-window",
                        "1e-30", "2e-30", "--out", str(out)], capture_output=True, text=True,
                       env=subprocess_env(), timeout=120)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "round-off" in r.stderr
    assert not out.exists()


def test_compression_cycle_stabilises_where_the_escapes_cannot(ladder, monkeypatch, tmp_path):
    """With the directional escapes switched off (MAX_ESCAPES = 0), the constructed saddle is
    made a stable minimum by the compression cycle (to 10x its dphi and back), at the same
    volume fraction and pressure.  The cycle's minimisations go through the checkpoint: a run
    resumed from it replays them and ends in the same state, bit for bit."""
    from parjam.files.checkpoint import Checkpoint

    d, (phi_c, packs) = ladder
    stable = packs[1]  # dphi = 1e-8
    saddle = saddles.along_soft_mode(stable, opened=2)
    monkeypatch.setattr(packing, "MAX_ESCAPES", 0)
    path = str(tmp_path / "cycle.h5")  # each rank its own (COMM_SELF checkpoints)
    runs = []
    for _ in range(2):
        ck = Checkpoint(path, PETSc.COMM_SELF, 1e-9, {"test": "cycle"})  # written every time
        # (on COMM_SELF: a shared FIRE run costs minutes on 2 ranks)
        lines = []
        jam = Jammer(PETSc.COMM_SELF, saddle, progress=lines.append, checkpoint=ck)
        try:
            res, info = jam.stabilise(MinResult("converged", 0.0, 0.0), phi=saddle.phi)
            final = jam.packing_for_file()
        finally:
            jam.destroy()
        runs.append((final, info, ck.loaded, jam.calls, lines))
    (pack, info, loaded, calls, _), (again, info2, resumed, calls2, lines2) = runs
    assert not loaded and resumed and calls == calls2 >= 2  # compress, decompress: replayed
    assert not any("recomputing" in line for line in lines2), lines2
    assert {k: v for k, v in info2.items() if k != "lowest_curvature_found"} == \
        {k: v for k, v in info.items() if k != "lowest_curvature_found"}
    assert info["negative_curvatures_found"] >= 1 and info["excess_found"] < 0
    assert info["escapes"] == 0 and info["cycles"] >= 1 and info["stable"] == 1
    after = network.analyze(pack)
    assert after.excess >= 0
    assert _dense_negatives(pack, info["curvature_shift"]) == 0
    assert pack.phi == pytest.approx(saddle.phi, rel=1e-14)
    assert after.pressure == pytest.approx(network.analyze(stable).pressure, rel=0.05)
    np.testing.assert_array_equal(pack.pos, again.pos)


def test_virial_dphi_disagreeing_with_the_label_is_flagged(ladder, capsys):
    """Every ladder state's own virial dphi agrees with its label; a state whose phi_c is not
    the one its network jams at (here: labelled 1e-4, really 1e-6 from jamming, as a state
    that re-jammed on the way) is recorded with dphi_virial_ok = 0 and said in one line."""
    from parjam.pack import ensemble
    from parjam.study import members

    d, (phi_c, packs) = ladder
    self_comm = env.petsc().COMM_SELF
    states = [packing.State(packing.block_rows(self_comm, p), MinResult("converged", 0.0, 0.0),
                            f"dphi{dphi:.1e}", {"phi_c": phi_c}) for dphi, p in zip(DPHIS, packs)]
    off = packing.State(packing.block_rows(self_comm, packs[-1]),
                        MinResult("converged", 0.0, 0.0), "dphi1.0e-04",
                        {"phi_c": packs[-1].phi - 1e-4})
    ensemble.virial_flags(states + [off])
    for dphi, st in zip(DPHIS, states):
        assert st.info["dphi_virial_ok"] == 1
        assert st.info["dphi_virial"] == pytest.approx(dphi, rel=0.02)
    assert off.info["dphi_virial_ok"] == 0
    assert off.info["dphi_virial"] == pytest.approx(1e-6, rel=0.02)
    capsys.readouterr()
    obs = ensemble.stability_observables(off, "member 0 dphi1.0e-04")
    err = capsys.readouterr().err
    assert obs["dphi_virial_ok"] == 0 and err.count("\n") == 1
    assert "re-jammed at another phi_c" in err and "1.00e-06" in err
    rows = [{"member": 0, "state": st.label, "dphi_virial_ok": st.info["dphi_virial_ok"]}
            for st in states + [off]]
    assert members.label_line(rows[:-1]) is None
    assert members.label_line(rows).startswith("labels: 1 state(s) re-jammed")


def test_unresolved_dphi_is_flagged_in_one_line_by_the_speaking_rank(ladder, capsys):
    """A state whose dphi phi_c does not resolve (resolution above RESOLVED_FRACTION of it) is
    recorded with dphi_resolved = 0, the others with 1; the line on stderr comes once, from the
    rank that speaks (a member shared by P ranks printed it P times before)."""
    from parjam.pack import ensemble

    d, (phi_c, packs) = ladder
    self_comm = env.petsc().COMM_SELF

    def states():
        return [packing.State(packing.block_rows(self_comm, p), MinResult("converged", 0.0, 0.0),
                              f"dphi{dphi:.1e}", {"phi_c": phi_c, "dphi": dphi})
                for dphi, p in zip(DPHIS, packs)]

    resolution = 2.0 * packing.RESOLVED_FRACTION * min(DPHIS)  # resolves all but the smallest
    capsys.readouterr()
    for speak, lines in ((True, 1), (False, 0)):
        sts = states()
        ensemble.resolution_flags(sts, resolution, "member 1 ", speak=speak)
        err = capsys.readouterr().err
        assert err.count("\n") == lines and err.count("below what phi_c resolves") == lines
        assert [st.info["dphi_resolved"] for st in sts] == [int(dp > min(DPHIS)) for dp in DPHIS]
        assert all(st.info["phi_c_resolution"] == resolution for st in sts)


def test_unjammed_ladder_step_keeps_the_jammed_states(shared_tmp, monkeypatch, capsys):
    """A ladder step that unjams (here: its energy floor raised above any jammed state, through
    the public Jammer.energy_floor) ends the member's ladder there: the states before it are
    written, each with ladder_unjammed_at in /observables; no manifest record (a rerun
    recomputes the member); parjam pack exits 3 and counts the stopped members in one line after
    its table."""
    from mpi4py import MPI

    from parjam import cli
    from parjam.files import manifest

    real = Jammer.energy_floor
    monkeypatch.setattr(Jammer, "energy_floor",
                        lambda self, dphi: np.inf if dphi >= 1e-3 else real(self, dphi))
    out = os.path.join(shared_tmp, "unjam")
    rc = cli.main(["pack", "--dim", "3", "--n", "32", "--seed", "1", "--members", "2",
                   "--dphi", "1e-6", "1e-3", "1e-2", "--checkpoint-every", "0", "-q",
                   "--out", out])
    assert rc == 3
    text = capsys.readouterr().out
    if MPI.COMM_WORLD.Get_rank() == 0:
        lines = [x for x in text.splitlines() if x.startswith("stopped:")]
        assert len(lines) == 1, text
        assert "2 of 2 member(s) stopped at dphi = 1e-03" in lines[0] and "unjammed" in lines[0]
        assert text.rstrip().endswith(lines[0])  # after the table, never inside it
        for m in (0, 1):
            files = sorted(os.listdir(out))
            assert f"member{m:04d}_phi_c.h5" in files and f"member{m:04d}_dphi1.0e-06.h5" in files
            assert not any(f.startswith(f"member{m:04d}_dphi1.0e-0{k}") for k in (2, 3)
                           for f in files)
            with h5py.File(os.path.join(out, f"member{m:04d}_dphi1.0e-06.h5"), "r") as f:
                assert h5md.observable(f, "ladder_unjammed_at") == pytest.approx(1e-3)
                assert h5md.observable(f, "stable") == 1
        assert not os.path.exists(manifest.record_path(out, 0))
        assert not os.path.exists(manifest.record_path(out, 1))
        assert manifest.load(out)["members"] == {}
