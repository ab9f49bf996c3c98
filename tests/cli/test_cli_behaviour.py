"""The command line as a user meets it: PETSc options no solver read are one-line warnings naming
the nearest valid option, a bad option value is a one-line error, a closed stdout ends quietly,
and `pack` reports progress for every member of every rank group, numbered as in its table."""

import os
import re
import subprocess
import sys

import pytest
from conftest import ROOT, subprocess_env

from parjam import options

PARJAM = [sys.executable, "-m", "parjam"]
REF = os.path.join(ROOT, "tests", "data", "ref_d3_mono_N128_dphi1e-03.h5")


def _run(args, cwd, mpi=0, timeout=300):
    cmd = PARJAM + args
    if mpi:
        cmd = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split() + \
            ["-n", str(mpi)] + cmd
    return subprocess.run(cmd, cwd=cwd, env=subprocess_env(), capture_output=True, text=True,
                          timeout=timeout)


def test_nearest_valid_option():
    assert options.suggestion("eps_view", "modes") == "modes_eps_view"
    assert options.suggestion("ksp_monitor", "pack") == "newton_ksp_monitor"
    assert options.suggestion("modes_eps_tyep", "modes") == "modes_eps_type"
    assert options.suggestion("log_veiw", "modes") == "log_view"
    assert options.suggestion("completely_unrelated_thing", "modes") is None


@pytest.mark.serial
def test_unused_and_misspelled_options_warn(tmp_path):
    r = _run(["modes", REF, "--k", "4", "--method", "sinvert", "--out", "s.h5", "-q",
              "-eps_view", "-modes_eps_tyep", "krylovschur", "-modes_eps_ncv", "20",
              "-newton_ksp_type", "cg"], tmp_path)
    assert r.returncode == 0, r.stderr
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("parjam: warning: -")]
    assert warnings == [
        "parjam: warning: -eps_view was not used; did you mean -modes_eps_view?",
        "parjam: warning: -modes_eps_tyep was not used; did you mean -modes_eps_type?",
        "parjam: warning: -newton_ksp_type was not used: no solver that reads it ran"]
    assert "ncv" not in r.stderr  # -modes_eps_ncv reached the solver: no warning


@pytest.mark.serial
@pytest.mark.parametrize("mpi", [0, 2])
def test_bad_option_value_is_one_line(tmp_path, mpi):
    r = _run(["modes", REF, "--k", "4", "--method", "sinvert", "--out", "s.h5", "-q",
              "-modes_eps_type", "bogus"], tmp_path, mpi=mpi)
    assert r.returncode == 2
    ours = [ln for ln in r.stderr.splitlines() if ln.startswith(("parjam", "[", "Traceback"))]
    assert ours == ["parjam: error: PETSc rejected an option: Unknown EPS type given: bogus "
                    "(PETSc options given: -modes_eps_type bogus)"]
    assert not os.path.exists(tmp_path / "s.h5")


@pytest.mark.serial
def test_closed_stdout_ends_quietly(tmp_path):
    files = " ".join([REF] * 40)
    cmd = " ".join(PARJAM) + f" analyze {files} | head -1; echo \"status=${{PIPESTATUS[0]}}\""
    r = subprocess.run(["bash", "-c", cmd], cwd=tmp_path, env=subprocess_env(),
                       capture_output=True, text=True, timeout=300)
    assert r.stdout.splitlines()[0] == REF
    status = int(re.search(r"status=(\d+)", r.stdout).group(1))
    assert status in (0, 141), r.stderr
    assert r.stderr == ""  # no traceback, no PETSc signal dump


@pytest.mark.serial
def test_progress_of_every_member_on_every_rank_group(tmp_path):
    r = _run(["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--members", "2",
              "--dphi", "1e-3", "--out", "o", "--seed", "3"], tmp_path, mpi=2)
    assert r.returncode == 0, r.stderr
    done = sorted(re.findall(r"member (\d+) of 2: done in", r.stderr))
    assert done == ["1", "2"]  # member 2 ran on rank 1's group (members counted from 1)
    # the table's rows (the stability line under it is not a row)
    table = [ln.split()[0] for ln in r.stdout.splitlines()[1:] if ln.split()[0].isdigit()]
    assert sorted(set(table)) == ["1", "2"]  # the table numbers members the same way


@pytest.mark.serial
def test_run_progress_of_every_member_on_every_rank_group(tmp_path):
    """parjam run on 2 ranks with 2 members: member 2 is computed by rank 1's group, and its
    stage lines still reach world rank 0's log, counted from 1 as in pack's messages."""
    (tmp_path / "s.toml").write_text(
        '[[system]]\nd = 2\nN = 16\ndispersity = "bi"\n[protocol]\ndphi = [1e-3]\n'
        '[ensemble]\nmembers = 2\nseed = 3\n[observables]\ncontacts = true\n')
    r = _run(["run", "s.toml", "--out", "o"], tmp_path, mpi=2)
    assert r.returncode == 0, r.stderr
    for stage in ("pack", "network"):
        done = sorted(re.findall(rf"run: {stage} \S+: member (\d+) of 2 in", r.stderr))
        assert done == ["1", "2"], (stage, r.stderr)
