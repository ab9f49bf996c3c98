"""Checkpoints inside a member (parjam.files.checkpoint): a `parjam pack` interrupted anywhere in a
member's protocol resumes from its last checkpoint, loses and repeats no minimisation work, and
ends with the same files, bitwise, as an uninterrupted run -- also when the member is shared by
two ranks, and when a run stopped on 2 ranks resumes on 1 or 3."""

import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from conftest import subprocess_env

from parjam import cli
from parjam.files import checkpointio, manifest
from parjam.files import checkpoint
from parjam.errors import ParjamError
from parjam.pack.engine import SlabEngine
from parjam.pack.forces import ForceField
from parjam.pack.minimize import FireParams, MinResult, fire
from parjam.pack.packing import random_packing
from parjam.testing.gather import gather
from parjam.testing.h5compare import differences

ARGS = ["pack", "--dim", "3", "--n", "64", "--seed", "4", "--dphi", "1e-6", "1e-2", "-q"]
STATES = ("phi_c", "dphi1.0e-06", "dphi1.0e-02")


class Stop(ParjamError):
    """The interruption (collective: raised on every rank at the same write)."""


def _pack(out, every="1e-9"):
    return cli.main(ARGS + ["--out", out, "--checkpoint-every", every])


@pytest.fixture(scope="module")
def reference(shared_tmp):
    out = os.path.join(shared_tmp, "ckpt-reference")
    assert _pack(out, every="0") == 0
    return out


@pytest.fixture
def evaluations(monkeypatch):
    """Counts every force evaluation of this process (plain, and those of the fused FIRE
    step)."""
    count = {"n": 0}
    for cls, name in ((ForceField, "evaluate"), (SlabEngine, "start"), (SlabEngine, "step")):
        real = getattr(cls, name)

        def counting(self, *args, real=real, **kw):
            count["n"] += 1
            return real(self, *args, **kw)

        monkeypatch.setattr(cls, name, counting)
    return count


def _attr(path, key):
    with h5py.File(path, "r") as f:
        return f["parameters"].attrs[key]


def _assert_same(out, reference):
    """Bitwise, on any number of ranks and whatever the ranks that wrote the checkpoint: a
    member shared by several ranks is the same bits as on one (exact sums, Newton's steps on
    one rank: tests/pack/test_rank_independence.py)."""
    for state in STATES:
        name = f"member0000_{state}.h5"
        a, b = os.path.join(out, name), os.path.join(reference, name)
        diff = differences(a, b)
        # the count includes the evaluation that restarts an interrupted FIRE run
        assert diff in ([], ["parameters/force_evaluations"]), (name, diff)


def test_fire_continues_bitwise_from_a_snapshot(world):
    """FIRE stopped at step 300 and continued from its FireState ends where an uninterrupted run
    of the same length does, bitwise (the new neighbour list changes no force)."""
    pack = random_packing(3, 96, 0.70, rng=np.random.default_rng(2))
    params = FireParams(max_steps=700)

    def field(pos):
        ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
        ff.set_positions(pos)
        return ff

    ff = field(pack.pos)
    ref = fire(ff, 1e-14, params=params)
    end = np.array(gather(ff))
    ff.destroy()

    ff = field(pack.pos)
    seen = []

    def hook(make_state):
        if len(seen) == 2:
            seen.append((np.array(gather(ff)), make_state()))
            raise Stop("stop")
        seen.append(None)

    with pytest.raises(Stop):
        fire(ff, 1e-14, params=params, snapshot=hook)
    ff.destroy()
    pos, state = seen[-1]
    assert state.step == 300
    ff = field(pos)
    res = fire(ff, 1e-14, params=params, start=state)
    assert (res.fire_steps, res.status) == (ref.fire_steps, ref.status) == (700, "not converged")
    assert res.energy == ref.energy
    assert np.array_equal(np.array(gather(ff)), end)
    ff.destroy()


@pytest.mark.parametrize("k", [1, 7, 100, 170])  # of 180: quench, its end, phi_c search, ladder
def test_pack_interrupted_at_the_kth_checkpoint_resumes_bitwise(world, shared_tmp, monkeypatch,
                                                                   reference, evaluations, k):
    """Interrupted right after its k-th checkpoint write (in the quench, the phi_c search or the
    ladder), the run resumes: the force evaluations of both runs add up to the uninterrupted
    run's (plus at most the one that restarts FIRE), and the files are the same bitwise."""
    out = os.path.join(shared_tmp, f"ckpt-k{k}")
    writes = {"n": 0}
    real = checkpoint.Checkpoint.write

    def interrupting(self):
        real(self)
        writes["n"] += 1
        if writes["n"] == k:
            raise Stop(f"stopped after checkpoint {k}")

    monkeypatch.setattr(checkpoint.Checkpoint, "write", interrupting)
    assert _pack(out) == Stop.exit_code
    path = checkpoint.path_for(out, 0)
    assert os.path.exists(path) and not os.path.exists(manifest.record_path(out, 0))
    first = evaluations["n"]
    monkeypatch.setattr(checkpoint.Checkpoint, "write", real)
    assert _pack(out) == 0
    resumed = evaluations["n"] - first
    total = int(_attr(os.path.join(reference, "member0000_dphi1.0e-02.h5"),
                      "force_evaluations"))
    # the same trajectory on any number of ranks: no evaluation lost or repeated
    assert 0 < resumed < total
    assert first + resumed - total in (0, 1)
    _assert_same(out, reference)
    assert not os.path.exists(os.path.join(out, checkpoint.DIRECTORY))


@pytest.mark.parametrize("content", ["foreign", "garbage"])
def test_foreign_or_unreadable_checkpoint_is_ignored(world, shared_tmp, reference, content):
    """A checkpoint of other parameters, or a damaged one, is set aside with a note: the member
    is computed from its random start, as in the reference."""
    out = os.path.join(shared_tmp, f"ckpt-{content}")
    path = checkpoint.path_for(out, 0)
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() == 0:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        if content == "garbage":
            with open(path, "wb") as fh:
                fh.write(b"not an HDF5 file")
        else:
            rec = {"file": "done00000.g0000001.h5", "L": 1.0, "force_calls": 1,
                   "result": MinResult("converged", 0.0, 0.0)}
            checkpoint.write_file(path, '{"other": 1}', [rec], None)
    MPI.COMM_WORLD.Barrier()
    assert _pack(out) == 0
    _assert_same(out, reference)


def test_record_of_another_volume_fraction_ends_the_replay(world, shared_tmp, monkeypatch,
                                                            reference):
    """A record whose box is not the one the protocol asks for (e.g. written by a protocol that
    went another way) is recomputed, with those after it: the result is still the reference."""
    out = os.path.join(shared_tmp, "ckpt-moved")
    real = checkpoint.Checkpoint.write
    writes = {"n": 0}

    def interrupting(self):
        real(self)
        writes["n"] += 1
        if writes["n"] == 100:
            raise Stop("stopped")

    monkeypatch.setattr(checkpoint.Checkpoint, "write", interrupting)
    assert _pack(out) == Stop.exit_code
    monkeypatch.setattr(checkpoint.Checkpoint, "write", real)
    if world.getRank() == 0:
        with h5py.File(checkpoint.path_for(out, 0), "r+") as f:
            assert len(f["done"]) >= 3
            f["done/00002"].attrs["L"] *= 1.001
    world.tompi4py().Barrier()
    assert _pack(out) == 0
    _assert_same(out, reference)


@pytest.mark.serial
def test_unwritable_checkpoint_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    """A checkpoint that cannot be written (full disk) ends the run with a one-line error and
    exit status 2, and no member file (on several ranks it aborts them all: a non-collective
    error, tests/hostile/test_robustness_mpi.py)."""

    def full_disk(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint, "write_file", full_disk)
    out = str(tmp_path / "run")
    assert _pack(out) == 2
    err = capsys.readouterr().err
    assert "parjam: error: cannot write checkpoint" in err and "No space left" in err, err
    assert "Traceback" not in err
    assert not [n for n in os.listdir(out) if n.endswith(".h5")]


def test_negative_checkpoint_interval_is_refused(shared_tmp):
    out = os.path.join(shared_tmp, "ckpt-bad")
    assert cli.main(ARGS + ["--out", out, "--checkpoint-every", "-1"]) == 2
    assert not os.path.exists(out)


@pytest.mark.serial
def test_killed_process_resumes_from_its_checkpoint(tmp_path):
    """SIGKILLed right after its first checkpoint (PARJAM_FAULT), `parjam pack` run again says it
    resumes and gives the uninterrupted run's files."""
    cmd = [sys.executable, "-m", "parjam"] + ARGS[:-1] + ["--checkpoint-every", "1e-9"]
    ref = subprocess.run(cmd + ["--out", str(tmp_path / "ref"), "-q"], env=subprocess_env(),
                         capture_output=True, text=True, timeout=300)
    assert ref.returncode == 0, ref.stderr
    out = str(tmp_path / "run")
    r = subprocess.run(cmd + ["--out", out, "-q"], env=subprocess_env(
        PARJAM_FAULT="pack.checkpoint@0:kill"), capture_output=True, text=True, timeout=300)
    assert r.returncode != 0
    assert os.path.exists(checkpoint.path_for(out, 0))
    r = subprocess.run(cmd + ["--out", out], env=subprocess_env(), capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "resuming from" in r.stderr and "one in progress" in r.stderr, r.stderr
    _assert_same(out, str(tmp_path / "ref"))


def test_finished_positions_go_to_a_piece_by_rows_and_come_back(world, shared_tmp):
    """A finished minimisation's positions are held by no rank after ``finish``: they are in
    its piece file, exactly, written from every rank's block rows; a fresh checkpoint replays
    them into every rank's block rows, bitwise, each rank reading its own rows."""
    pack = random_packing(3, 96, 0.70, rng=np.random.default_rng(3))
    path = os.path.join(shared_tmp, "rows", "member0000.h5")
    ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
    try:
        ff.set_positions(pack.pos)
        ck = checkpoint.Checkpoint(path, world, 1e-9, {"test": "rows"})
        ck.finish(0, ff, pack.L, MinResult("converged", 1.0, 0.0), 5)
        rec = ck.finished(0)
        assert "pos" not in rec and rec["L"] == pack.L and rec["force_calls"] == 5
        with h5py.File(os.path.join(checkpointio.pieces_dir(path), rec["file"]), "r") as f:
            assert np.array_equal(f["pos"][()], pack.pos)
        world.tompi4py().Barrier()
        again = checkpoint.Checkpoint(path, world, 1e-9, {"test": "rows"})
        assert again.loaded
        ff.set_positions(np.zeros_like(pack.pos))
        again.replay_rows(0, ff)
        assert np.array_equal(ff.local(ff.x), pack.pos[ff.lo:ff.hi])
    finally:
        ff.destroy()


@pytest.mark.parametrize("step", ["done-piece", "snapshot-piece", "index"])
def test_stopped_between_the_steps_of_a_write_resumes(world, shared_tmp, monkeypatch, reference,
                                                      step):
    """Stopped between the steps of a checkpoint write -- after the piece of a finished
    minimisation, or of a snapshot, but before the index that would name it; or after the index
    but before the pieces it no longer names are removed -- the index on disk is valid (it names
    only whole pieces, the others are orphans): the run resumes from it and ends with the
    reference's files and no checkpoint left."""
    out = os.path.join(shared_tmp, f"ckpt-stop-{step}")
    seen = {"n": 0}
    if step == "index":
        monkeypatch.setattr(checkpointio, "remove_unnamed", lambda index, keep: None)
        real = checkpoint.Checkpoint.write

        def stopping(self):
            real(self)
            seen["n"] += 1
            if seen["n"] == 100:
                raise Stop("stopped before the unnamed pieces are removed")

        monkeypatch.setattr(checkpoint.Checkpoint, "write", stopping)
    else:
        # of a run's 9 finished minimisations and ~190 snapshots
        kind, k = ("pending", 100) if step == "snapshot-piece" else ("done", 5)
        real = checkpointio.write_rows

        def stopping(comm, piece, blocks):
            real(comm, piece, blocks)
            if os.path.basename(piece).startswith(kind):
                seen["n"] += 1
                if seen["n"] == k:
                    raise Stop(f"stopped after {piece}")

        monkeypatch.setattr(checkpointio, "write_rows", stopping)
    assert _pack(out) == Stop.exit_code
    monkeypatch.undo()
    path = checkpoint.path_for(out, 0)
    if world.getRank() == 0:
        index = checkpointio.read_index(path)  # valid, its pieces all there
        named = {rec["file"] for rec in index["done"]}
        named |= {index["pending"]["file"]} if index["pending"] else set()
        orphans = set(os.listdir(checkpointio.pieces_dir(path))) - named
        assert orphans and all(n.startswith("pending" if step != "done-piece" else "done")
                               for n in orphans), orphans
    world.tompi4py().Barrier()
    assert _pack(out) == 0
    _assert_same(out, reference)
    assert not os.path.exists(os.path.join(out, checkpoint.DIRECTORY))


def test_checkpoint_of_the_format_before_is_ignored_with_a_note(world, shared_tmp, reference):
    """A checkpoint of parjam's earlier format (FORMAT 1: one HDF5 file holding every record's
    positions) is not read: one note says so, and the member is computed afresh."""
    out = os.path.join(shared_tmp, "ckpt-format1")
    path = checkpoint.path_for(out, 0)
    if world.getRank() == 0:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with h5py.File(path, "w") as f:  # the layout of that format
            f.attrs.update({"format": 1, "params": "{}"})
            g = f.create_group("done/00000")
            g["pos"] = np.zeros((64, 3))
            g.attrs.update({"L": 1.0, "force_calls": 1, "status": "converged", "energy": 0.0,
                            "fmax": 0.0, "fire_steps": 1, "newton_steps": 0})
    world.tompi4py().Barrier()
    notes = []
    ck = checkpoint.Checkpoint(path, world, 1e-9, {"member": 0}, progress=notes.append)
    assert not ck.loaded
    assert len(notes) == 1 and "earlier format 1" in notes[0] and "ignored" in notes[0], notes
    assert _pack(out) == 0
    _assert_same(out, reference)
    assert not os.path.exists(os.path.join(out, checkpoint.DIRECTORY))


STOP_AT = """
import sys
from parjam import cli; from parjam.files import checkpoint
from parjam.errors import ParjamError
real, k, seen = checkpoint.Checkpoint.write, int(sys.argv[1]), []
def stopping(self):
    real(self)
    seen.append(1)
    if len(seen) == k:
        raise ParjamError("stopped")
checkpoint.Checkpoint.write = stopping
sys.exit(cli.main(sys.argv[2:]))
"""


@pytest.mark.serial
def test_checkpoint_written_on_2_ranks_resumes_on_1_and_3(tmp_path):
    """The files are in particle-id order, whatever the ranks that wrote them: a checkpoint of a
    member shared by 2 ranks (stopped at its 100th write of ~200) resumes on 1 and on 3 ranks, each
    reading its own rows, to the same files, bitwise, as the uninterrupted 2-rank run."""
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    args = ARGS[:-1] + ["--checkpoint-every", "1e-9"]

    def run(ranks, out, *head):
        cmd = ([] if ranks == 1 else mpirun + ["-n", str(ranks)]) + [sys.executable, *head]
        return subprocess.run(cmd + args + ["--out", str(out)], env=subprocess_env(),
                              capture_output=True, text=True, timeout=600)

    ref = run(2, tmp_path / "ref", "-m", "parjam")
    assert ref.returncode == 0, ref.stderr
    r = run(2, tmp_path / "run", "-c", STOP_AT, "100")
    assert r.returncode == 2 and "stopped" in r.stderr, r.stderr
    for ranks in (1, 3):
        out = tmp_path / f"on{ranks}"
        shutil.copytree(tmp_path / "run", out)
        r = run(ranks, out, "-m", "parjam")
        assert r.returncode == 0, r.stderr
        assert "resuming from" in r.stderr and "minimisations finished" in r.stderr, r.stderr
        _assert_same(str(out), str(tmp_path / "ref"))
        assert not os.path.exists(out / checkpoint.DIRECTORY)
