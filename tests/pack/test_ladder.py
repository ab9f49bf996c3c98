"""A ladder step that unjams is made again from the last jammed state, in smaller steps with
Newton first (parjam.pack.packing.Jammer.rejam): inside the member's basin it finds the same
minimum as the direct minimisation; a member that unjams even so is stopped, its earlier states
written, and reported in one line after the table and in the manifest (exit 3)."""

import json
import os

import numpy as np
import pytest

from parjam import cli, env
from parjam.errors import UnjammedError
from parjam.files import rowio
from parjam.pack import filestart
from parjam.pack.packing import Jammer

from conftest import DATA

PETSc = env.petsc()
WORLD = PETSc.COMM_WORLD
START = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-06.h5")  # a jammed state at dphi = 1e-6


def jammer_from(path, comm=WORLD):
    rows = rowio.read_rows(comm, path)
    about = filestart.describe(comm, rows)
    return Jammer(comm, filestart.start_rows(comm, rows, 2.0, about.phi))


def test_made_again_in_smaller_steps_it_is_the_same_minimum():
    """From a jammed state at dphi = 1e-6 to 1e-4: the direct FIRE + Newton minimisation and the
    retry in REJAM_STEPS sub-steps, each a stable state, reach the same minimum (same network,
    energy and pressure to 1e-6): the retry stays in the member's basin."""
    direct = jammer_from(START)
    phi_c = direct.phi - 1e-6
    try:
        a = direct.at_phi(phi_c + 1e-4, "dphi1.0e-04", e_stop=direct.energy_floor(1e-4))
        net_a = a.rows.network()
    finally:
        direct.destroy()
    again = jammer_from(START)
    try:
        b = again.rejam(again.state_rows(), "dphi1.0e-04", phi_c=phi_c, dphi=1e-4)
        net_b = b.rows.network()
    finally:
        again.destroy()
    assert b.info["rejammed"] == 1 and b.info["stable"] == 1 and b.info["dphi"] == 1e-4
    assert b.phi == pytest.approx(phi_c + 1e-4, rel=1e-14)
    assert (net_b.n_active, net_b.n_contacts) == (net_a.n_active, net_a.n_contacts)
    assert net_b.n_contacts >= net_b.n_iso
    assert net_b.energy == pytest.approx(net_a.energy, rel=1e-6)
    assert net_b.pressure == pytest.approx(net_a.pressure, rel=1e-6)


def test_a_step_that_unjams_is_retried_and_recovered(monkeypatch):
    """The ladder's first attempt at dphi = 1e-4 is made to unjam (as FIRE's momentum can carry a
    member across a saddle): the ladder goes back and makes the step again, and the state is
    labelled, jammed and stable."""
    real = Jammer.at_phi
    calls = []

    def overshoot(self, phi, label, e_stop=None, newton_first=False, **info):
        calls.append(newton_first)
        if not newton_first:
            self.rescale(phi * 0.99)  # somewhere else entirely: the retry must go back
            raise UnjammedError("unjammed (test)", collective=False)
        return real(self, phi, label, e_stop=e_stop, newton_first=newton_first, **info)

    monkeypatch.setattr(Jammer, "at_phi", overshoot)
    jam = jammer_from(START)
    phi_c = jam.phi - 1e-6
    try:
        (st,) = jam.ladder(phi_c, [1e-4])
        net = st.rows.network()
    finally:
        jam.destroy()
    assert calls[0] is False and all(calls[1:]) and len(calls) >= 2
    assert st.label == "dphi1.0e-04" and st.info["rejammed"] == 1 and st.info["stable"] == 1
    assert net.n_contacts >= net.n_iso and net.pressure > 0
    assert st.info["dphi_virial"] == pytest.approx(1e-4, rel=0.05)  # jammed at this phi_c


def test_a_member_that_unjams_again_is_stopped_counted_and_reported(tmp_path, monkeypatch,
                                                                     capsys):
    """dphi = 1e-2 unjams, also when made again: the dphi = 1e-4 state is written, the run
    exits 3, the table is followed by one 'stopped:' line (nothing inside the table), and the
    manifest counts the member as stopped at 1e-2."""
    real = Jammer.at_phi

    def unjams_at_1e2(self, phi, label, e_stop=None, newton_first=False, **info):
        if label == "dphi1.0e-02":
            raise UnjammedError("unjammed (test)", collective=False)
        return real(self, phi, label, e_stop=e_stop, newton_first=newton_first, **info)

    monkeypatch.setattr(Jammer, "at_phi", unjams_at_1e2)
    out = tmp_path / "run" if WORLD.getSize() == 1 else None
    out = str(out) if out else WORLD.tompi4py().bcast(str(tmp_path / "run"), root=0)
    code = cli.main(["pack", "--dim", "2", "--n", "32", "--dispersity", "bi", "--seed", "2",
                     "--dphi", "1e-4", "1e-2", "--out", out, "--no-phic-file", "-q"])
    assert code == UnjammedError.exit_code == 3
    if WORLD.getRank() != 0:
        return
    text = capsys.readouterr().out.strip().splitlines()
    assert text[-1].startswith("stopped: 1 of 1 member(s) stopped at dphi = 1e-02")
    table = text[:-1]
    assert not any(line.startswith("stopped") for line in table)
    assert any("dphi1.0e-04" in line for line in table)
    assert os.path.isfile(os.path.join(out, "member0000_dphi1.0e-04.h5"))
    assert not os.path.exists(os.path.join(out, "member0000_dphi1.0e-02.h5"))
    with open(os.path.join(out, "manifest.json")) as fh:
        man = json.load(fh)
    assert man["stopped"] == {"0": 1e-2} and man["members"] == {}
    assert np.isfinite(man["stopped"]["0"])
