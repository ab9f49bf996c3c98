"""MPI faults: a failure on one rank ends every rank with its message (no hang), for each way a
rank can fail (a one-rank ParjamError, a bug, the process killed), at the start of a command and
in the middle of an ensemble; and the MPI test runner survives a test failing on one rank."""

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import subprocess_env

LIMIT = 120  # seconds: far above the few seconds these runs take; a hang would exceed it


def _mpirun(args, cwd, **env):
    cmd = ["mpirun", "--oversubscribe", "-n", "2", sys.executable] + args
    return subprocess.run(cmd, cwd=cwd, env=subprocess_env(**env), capture_output=True, text=True,
                          timeout=LIMIT)


@pytest.mark.serial
@pytest.mark.parametrize("kind,message", [
    ("error", "parjam: error: [rank 1] injected error at command"),
    ("crash", "parjam: error: [rank 1] InjectedCrash: injected crash at command"),
    ("kill", "exited on signal 9"),
])
def test_one_rank_fails_at_command_start(tmp_path, kind, message):
    """Rank 0 goes on into the command's collectives; rank 1 fails first: both end."""
    r = _mpirun(["-m", "parjam", "info"], tmp_path, PARJAM_FAULT=f"command@1:{kind}")
    assert r.returncode != 0
    assert message in r.stderr, r.stderr


@pytest.mark.serial
def test_one_rank_fails_in_the_middle_of_an_ensemble(tmp_path):
    """Rank 1 fails after its first member while rank 0 computes or waits in the final gather;
    the job ends with the message, and only complete files exist (no temporaries)."""
    r = _mpirun(["-m", "parjam", "pack", "--dim", "2", "--n", "32", "--dispersity", "bi",
                 "--members", "4", "--dphi", "1e-3", "--out", "o", "-q"], tmp_path,
                PARJAM_FAULT="pack.member@1:error")
    assert r.returncode != 0
    assert "parjam: error: [rank 1] injected error at pack.member" in r.stderr, r.stderr
    names = os.listdir(tmp_path / "o")
    assert "member0001_phi_c.h5" in names and "member0001_dphi1.0e-03.h5" in names
    assert not [n for n in names if ".tmp" in n]


@pytest.mark.serial
@pytest.mark.parametrize("command", [
    ["info"],  # rank 0 finishes the command and learns at the closing reduction
    ["pack", "--dim", "2", "--n", "32", "--dispersity", "bi", "--members", "1", "--dphi",
     "1e-3", "--out", "o", "-q"],  # rank 0 is stuck in the shared member's collectives
])
def test_one_rank_raises_a_collective_error(tmp_path, command):
    """An error marked collective but raised on one rank only (a mislabelled error) used to
    leave that rank waiting in PetscFinalize while the others waited in the command: now both
    end, with the message and a non-zero status, within PARJAM_ERROR_WAIT."""
    r = _mpirun(["-m", "parjam", *command], tmp_path, PARJAM_FAULT="command@1:collective",
                PARJAM_ERROR_WAIT="5")
    assert r.returncode != 0
    assert "parjam: error: [rank 1] injected collective error at command" in r.stderr, r.stderr


def test_fault_variable_is_validated():
    from parjam import faults
    from parjam.errors import ParjamError

    assert faults.parse("pack.member@1:kill") == ("pack.member", 1, "kill")
    assert faults.parse("command@0") == ("command", 0, "error")
    for bad in ("nowhere@1", "command@x", "command@1:explode", "command"):
        with pytest.raises(ParjamError):
            faults.parse(bad)


RUNNER_TESTS = textwrap.dedent("""
    from mpi4py import MPI
    import pytest

    def test_a_lone_failure_without_collective():
        assert MPI.COMM_WORLD.Get_rank() == 0, "rank 1 fails alone"

    def test_b_collectives_still_work():
        assert MPI.COMM_WORLD.allreduce(1) == MPI.COMM_WORLD.Get_size()

    def test_c_lone_failure_before_a_collective():
        if MPI.COMM_WORLD.Get_rank() == 1 and {stuck}:
            assert False, "rank 1 fails before the barrier"
        MPI.COMM_WORLD.Barrier()
""")


def _run_runner(tmp_path, stuck):
    (tmp_path / "test_fake.py").write_text(RUNNER_TESTS.format(stuck=stuck))
    return _mpirun(["-m", "parjam.testing.mpi_pytest", "-q", "--color=no", "-p", "no:cacheprovider",
                    "test_fake.py"], tmp_path, PARJAM_MPI_TEST_TIMEOUT="5")


@pytest.mark.serial
def test_runner_reports_a_lone_failure_and_goes_on(tmp_path):
    """A test failing on rank 1 only is reported by rank 0 with rank 1's message; the next
    tests (with collectives) still run and pass; the run fails."""
    r = _run_runner(tmp_path, stuck=False)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "failed on rank 1" in r.stdout and "rank 1 fails alone" in r.stdout, r.stdout
    assert "1 failed, 3 passed" in r.stdout, r.stdout


@pytest.mark.serial
def test_runner_aborts_when_a_lone_failure_would_deadlock(tmp_path):
    """Rank 1 fails before a barrier rank 0 waits in: rank 1 aborts the job after the timeout
    (5 s here) with the test's name, instead of deadlocking the next collective."""
    r = _run_runner(tmp_path, stuck=True)
    assert r.returncode != 0
    assert "test_c_lone_failure_before_a_collective failed on rank 1" in r.stderr, r.stderr
