"""First-contact frictions: progress stamped in world rank 0's time order and members
counted from 1, units in the CLI's tables, a warning when -modes_eps_nev contradicts --k."""

import os
import re
import time

import pytest

from parjam import cli, env
from parjam.progress import Progress, Relay, member

MPI = env.petsc().COMM_WORLD.tompi4py()
STAMP = re.compile(r"^\[\s*([0-9.]+) s\] (.*)$")


def _stamps(err):
    return [(float(m.group(1)), m.group(2)) for m in map(STAMP.match, err.splitlines()) if m]


def test_relayed_lines_never_go_back_in_time(capfd):
    """Rank 1's clock starts 0.6 s after rank 0's and its line reaches rank 0 while rank 0 is
    busy: the old relay printed it with rank 1's own stamp (0.2 s) after rank 0's 0.4 s line.
    Every line now carries rank 0's time at printing, in order."""
    rank = MPI.Get_rank()
    relay = Relay(MPI)
    if rank == 0:
        p = Progress(MPI, relay=relay)
        time.sleep(0.4)
        p("zero at 0.4")
        time.sleep(0.6)  # rank 1 speaks meanwhile
        p("zero at 1.0")
    else:
        time.sleep(0.6)
        from mpi4py import MPI as mpi

        p = Progress(mpi.COMM_SELF, relay=relay)  # a group's rank 0 (its own clock before)
        time.sleep(0.2)
        p("one at 0.8")
    relay.close()
    lines = _stamps(capfd.readouterr().err)
    if rank != 0:
        assert lines == []  # only world rank 0 prints
        return
    times = [t for t, _ in lines]
    assert times == sorted(times)
    texts = [text for _, text in lines]
    assert texts[0] == "zero at 0.4" and len(texts) == 1 + MPI.Get_size()
    if MPI.Get_size() == 2:  # printed when it arrived (before or after rank 0's second line),
        # stamped by rank 0's clock: never earlier than it was made
        (relayed,) = [t for t, text in lines if text == "one at 0.8"]
        assert relayed >= 0.8 - 0.05


def test_members_are_counted_from_one():
    assert member(0) == "member 1" and member(7, 8) == "member 8 of 8"


def test_pack_table_names_units_and_counts_members_from_one(shared_tmp, capfd):
    out = os.path.join(shared_tmp, "frictions-pack")
    assert cli.main(["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--members", "2",
                     "--dphi", "1e-2", "--out", out, "--checkpoint-every", "0"]) == 0
    captured = capfd.readouterr()
    if MPI.Get_rank() != 0:
        return
    lines = captured.out.splitlines()
    head = next(k for k, ln in enumerate(lines) if ln.split()[:2] == ["member", "state"])
    assert lines[head + 1].split() == ["[eps", "sigma^-2]", "[eps/sigma]"]
    # the unit sits under its column
    assert lines[head + 1].index("[eps sigma^-2]") + len("[eps sigma^-2]") == \
        lines[head].index(" p ") + len(" p")
    rows = [ln.split() for ln in lines[head + 2:] if ln.split() and ln.split()[0].isdigit()]
    assert sorted({r[0] for r in rows}) == ["1", "2"]
    done = re.findall(r"member (\d) of 2: done in", captured.err)
    assert sorted(done) == ["1", "2"]
    assert _stamps(captured.err) and [t for t, _ in _stamps(captured.err)] == sorted(
        t for t, _ in _stamps(captured.err))
    # member 1's files are member0000_*: the table's member 1 is the file's index 0
    from parjam.files import h5md

    p = h5md.read_packing(os.path.join(out, "member0000_dphi1.0e-02.h5"))
    first = [r for r in rows if r[0] == "1" and r[1] == "dphi1.0e-02"][0]
    assert float(first[3]) == pytest.approx(p.phi, abs=1e-10)


def test_analyze_and_modes_lines_carry_units(shared_tmp, capfd):
    from conftest import DATA

    path = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")
    assert cli.main(["analyze", path]) == 0
    out = capfd.readouterr().out
    if MPI.Get_rank() == 0:
        assert re.search(r"pressure\s+\S+ \[eps sigma\^-3\]", out)
        assert re.search(r"energy_per_particle\s+\S+ \[eps\]", out)
        assert re.search(r"max_force\s+\S+ \[eps/sigma\]", out)
        assert re.search(r"\n  z\s+[0-9.]+\n", out)  # dimensionless: no unit
    spec = os.path.join(shared_tmp, "frictions-s.h5")
    assert cli.main(["modes", path, "--k", "8", "--out", spec, "-q"]) == 0
    captured = capfd.readouterr()
    if MPI.Get_rank() == 0:
        assert re.search(r"omega \S+ \.\. \S+ \[tau\^-1\]", captured.out)
        assert re.search(r"D0 = \S+ \[tau\], omega\* = \S+ \[tau\^-1\]", captured.out)


@pytest.mark.serial
def test_modes_eps_nev_against_k_warns_in_one_line(tmp_path):
    """-modes_eps_nev 3 with --k 8 (shift-and-invert): one warning line before the work (it
    ended in exit 4 without a word); the same nev as --k: no warning."""
    import subprocess
    import sys

    from conftest import DATA, subprocess_env

    path = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")

    def modes(*extra):
        return subprocess.run([sys.executable, "-m", "parjam", "modes", path, "--k", "8",
                               "--method", "sinvert", "--out", str(tmp_path / "s.h5"), "-q",
                               *extra], env=subprocess_env(), capture_output=True, text=True,
                              timeout=300)

    r = modes("-modes_eps_nev", "3")
    warn = [ln for ln in r.stderr.splitlines() if "-modes_eps_nev" in ln]
    assert len(warn) == 1 and warn[0].startswith(
        "parjam: warning: -modes_eps_nev 3 contradicts --k 8"), r.stderr
    assert r.returncode in (0, 4) and "Traceback" not in r.stderr
    r = modes("-modes_eps_nev", "8")
    assert r.returncode == 0 and "contradicts" not in r.stderr, r.stderr
