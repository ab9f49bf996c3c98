"""Resume without loss: `parjam pack` killed (SIGTERM, SIGKILL, a rank killed under mpirun) in the
middle of an ensemble and restarted with the same command finishes without recomputing finished
members, leaves no temporary, corrupt or duplicate file, and gives the same files (datasets,
bitwise) as an uninterrupted run.  A directory of other parameters is refused."""

import glob
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import subprocess_env

from parjam import cli
from parjam.files import manifest
from parjam.files.h5md import read_packing, sha256
from parjam.testing.h5compare import differences

MEMBERS = 5
ARGS = ["pack", "--dim", "2", "--n", "32", "--dispersity", "bi", "--members", str(MEMBERS),
        "--seed", "5", "--dphi", "1e-4", "1e-2", "-q"]
STATES = ("phi_c", "dphi1.0e-04", "dphi1.0e-02")


def _cmd(out, mpi=0, quiet=True):
    cmd = [sys.executable, "-m", "parjam"] + ARGS[:-1] + ["--out", str(out)] + ["-q"] * quiet
    return (["mpirun", "--oversubscribe", "-n", str(mpi)] + cmd) if mpi else cmd


def _run(out, mpi=0, timeout=300, quiet=True, **env):
    return subprocess.run(_cmd(out, mpi, quiet), env=subprocess_env(**env), capture_output=True,
                          text=True, timeout=timeout)


def _records(out):
    return sorted(glob.glob(os.path.join(out, manifest.RECORDS, "member*.json")))


def _snapshot(out):
    """(inode, mtime_ns) of every packing file: unchanged if the file was not rewritten."""
    return {os.path.basename(p): (os.stat(p).st_ino, os.stat(p).st_mtime_ns)
            for p in glob.glob(os.path.join(out, "member*.h5"))}


def _check_complete(out):
    names = sorted(os.listdir(out))
    expected = sorted(f"member{m:04d}_{s}.h5" for m in range(MEMBERS) for s in STATES)
    assert [n for n in names if n.endswith(".h5")] == expected
    assert not [n for n in names if ".tmp" in n]
    assert not [n for n in os.listdir(os.path.join(out, manifest.RECORDS)) if ".tmp" in n]
    man = json.load(open(os.path.join(out, manifest.NAME)))
    assert sorted(man["members"]) == [str(m) for m in range(MEMBERS)]
    for files in man["members"].values():
        for name, digest in files.items():
            assert sha256(os.path.join(out, name)) == digest
            read_packing(os.path.join(out, name))  # valid, complete file


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("full") / "run"
    r = _run(out)
    assert r.returncode == 0, r.stderr
    return out


def _same_as(out, reference):
    for name in sorted(os.listdir(reference)):
        if name.endswith(".h5"):
            assert differences(os.path.join(out, name), os.path.join(reference, name)) == [], \
                name


@pytest.mark.serial
def test_sigterm_then_sigkill_then_resume(tmp_path, uninterrupted):
    """Killed twice in the middle of the ensemble (SIGTERM once members are done, then SIGKILL),
    the same command finishes the rest: finished files untouched, the result equals an
    uninterrupted run's."""
    out = tmp_path / "run"
    for sig in (signal.SIGTERM, signal.SIGKILL):
        proc = subprocess.Popen(_cmd(out), env=subprocess_env(), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        target = len(_records(out)) + 1
        deadline = time.time() + 240
        while len(_records(out)) < target and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be killed"
        proc.send_signal(sig)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()  # SIGTERM ignored: SIGKILL, as a batch system does
            proc.wait()
        err = proc.stderr.read()
        assert proc.returncode != 0
        if sig == signal.SIGTERM:
            assert "interrupted" in err and "Traceback" not in err, err
        assert not [n for n in os.listdir(out) if ".tmp" in n and sig == signal.SIGTERM]
        assert len(_records(out)) < MEMBERS
    finished = _recorded(out)
    before = _snapshot(out)
    r = _run(out, quiet=False)
    assert r.returncode == 0, r.stderr
    assert f"resuming: {len(finished)} of {MEMBERS} members already finished" in r.stderr
    _assert_not_recomputed(out, finished, before)
    _check_complete(out)
    _same_as(out, uninterrupted)


def _recorded(out):
    return {json.load(open(p))["member"] for p in _records(out)}


def _assert_not_recomputed(out, members, before):
    now = _snapshot(out)
    for m in members:
        for state in STATES:
            name = f"member{m:04d}_{state}.h5"
            assert now[name] == before[name], f"{name} was recomputed"


@pytest.mark.serial
def test_rank_killed_under_mpirun_then_resume(tmp_path, uninterrupted):
    """Rank 1 SIGKILLed after its first member (PARJAM_FAULT): mpirun ends the job without a
    hang; the restart on 2 ranks completes, bitwise equal to the 1-rank uninterrupted run."""
    out = tmp_path / "run"
    r = _run(out, mpi=2, timeout=240, PARJAM_FAULT="pack.member@1:kill")
    assert r.returncode != 0
    assert 1 <= len(_records(out)) < MEMBERS
    finished, before = _recorded(out), _snapshot(out)
    r = _run(out, mpi=2, timeout=240)
    assert r.returncode == 0, r.stderr
    _assert_not_recomputed(out, finished, before)
    _check_complete(out)
    _same_as(out, uninterrupted)


@pytest.mark.serial
def test_damaged_files_are_recomputed_and_stale_temporaries_removed(tmp_path, uninterrupted):
    out = tmp_path / "run"
    r = _run(out, PARJAM_FAULT="pack.member@0:kill")  # dies right after member 0's record
    assert r.returncode != 0 and len(_records(out)) == 1
    victim = out / "member0000_dphi1.0e-02.h5"
    raw = victim.read_bytes()
    victim.write_bytes(raw[: len(raw) // 2])  # truncated after the fact: sha256 mismatch
    stale = out / ".member0001_phi_c.h5.tmp999999999"
    stale.write_bytes(b"half a file")
    r = _run(out)
    assert r.returncode == 0, r.stderr
    assert not stale.exists()
    _check_complete(out)
    _same_as(out, uninterrupted)


def test_other_parameters_are_refused_in_process(shared_tmp):
    """In-process (both passes): a finished directory is skipped entirely; other parameters in
    the same directory are a one-line error, and nothing is written."""
    out = os.path.join(shared_tmp, "resume-params")
    small = ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--seed", "3",
             "--dphi", "1e-3", "--members", "2", "--out", out, "-q"]
    assert cli.main(small) == 0
    stamp = _snapshot(out)
    assert cli.main(small) == 0  # everything finished: nothing recomputed
    assert _snapshot(out) == stamp
    bad = list(small)
    bad[bad.index("1e-3")] = "1e-2"
    assert cli.main(bad) == 2
    assert _snapshot(out) == stamp
    assert not glob.glob(os.path.join(out, "*dphi1.0e-02*"))
