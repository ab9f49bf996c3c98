"""``parjam pack --from FILE`` by rows (parjam.pack.filestart): each rank reads only its own
rows of the file, and what the command makes of them is what the whole-file start made (main's
``importer.from_file`` and ``Jammer(comm, pack)``): the description (d, N, phi bitwise, the
dispersity label and ratio), the Jammer's block rows, the files of the protocol (bitwise on one
rank; to round-off where ranks share the member, as any two shared runs); the same files on 1,
2 and 3 ranks (3: a middle rank and an uneven row split, which 2 ranks cannot make); bad input
is one line and exit 2 before any work.  Serial and 2-rank passes; 3 ranks by a serial test."""

import contextlib
import io as pyio
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from conftest import ROOT, run_on_ranks, subprocess_env
from mpi4py import MPI

from parjam import cli, env
from parjam.files import h5md, importer, rowio
from parjam.net import active
from parjam.pack import filestart
from parjam.study import members
from parjam.commands import pack as pack_cmd
from parjam.errors import ParjamError
from parjam.pack.packing import block_rows, random_packing
from parjam.testing.h5compare import assert_same_member, differences

COMM = MPI.COMM_WORLD
WORLD = env.petsc().COMM_WORLD
REF = os.path.join(ROOT, "tests", "data", "ref_d2_bi_N128_dphi1e-03.h5")
PROTOCOL = ["--phic-method", "extrapolate", "--dphi", "1e-3", "--checkpoint-every", "0", "-q"]


def write_start(path, pos, diam, L, species=None, params=None):
    """A minimal H5MD packing file (rank 0): positions (one frame), diameters, box edges, and
    the species and /parameters only if given (foreign files may lack them)."""
    if COMM.Get_rank() == 0:
        with h5py.File(path, "w") as f:
            part = f.create_group("particles/all")
            part["position/value"] = pos[None]
            part["diameter"] = diam
            part["box/edges/value"] = np.full((1, pos.shape[1]), L)
            if species is not None:
                part["species"] = species
            if params is not None:
                g = f.create_group("parameters")
                for k, v in params.items():
                    g.attrs[k] = v
    COMM.Barrier()
    return path


@pytest.fixture(scope="module")
def starts(shared_tmp):
    """Unjammed starts of every kind: 3D mono without species or /parameters, 2D bi with
    species and epsilon, 3D poly with some positions outside the box (read_packing folds
    them), an odd N (uneven row blocks on 2 and 3 ranks)."""
    out = {}
    p = random_packing(3, 41, 0.62, rng=np.random.default_rng(3))
    out["mono"] = write_start(os.path.join(shared_tmp, "from-mono.h5"), p.pos, p.diam, p.L)
    p = random_packing(2, 37, 0.88, 2.0, "bi", 1.4, np.random.default_rng(4))
    out["bi"] = write_start(os.path.join(shared_tmp, "from-bi.h5"), p.pos, p.diam, p.L,
                            p.meta["species"] + 1, {"alpha": 2.5, "epsilon": 1.5})
    p = random_packing(3, 43, 0.70, 2.0, "poly", 1.3, np.random.default_rng(5))
    pos = p.pos + p.L * np.random.default_rng(6).integers(-2, 3, p.pos.shape)
    out["poly"] = write_start(os.path.join(shared_tmp, "from-poly.h5"), pos, p.diam, p.L,
                              np.zeros(p.n, np.int64))
    return out


@pytest.mark.parametrize("kind", ["mono", "bi", "poly"])
def test_rows_and_description_are_the_whole_files(starts, kind):
    """describe and start_rows on these ranks against read_packing and main's
    importer.from_file + packing.block_rows: every number bitwise."""
    path = starts[kind]
    whole = h5md.read_packing(path)
    about = filestart.describe(COMM, rowio.read_rows(COMM, path))
    assert (about.d, about.n) == (whole.d, whole.n)
    assert about.phi == whole.phi  # bitwise: exactsum in numpy's order
    assert about.dispersity == {1: "mono", 2: "bi"}.get(len(set(whole.diam.tolist())), "poly")
    assert about.dispersity == kind
    assert about.ratio == float(whole.diam.max() / whole.diam.min())
    new = filestart.start_rows(WORLD, rowio.read_rows(WORLD, path), 2.5, about.phi)
    old = block_rows(WORLD, importer.from_file(path, 2.5))
    for name in ("n", "L", "alpha", "eps", "phi", "lo", "row_meta"):
        assert getattr(new, name) == getattr(old, name), name
    assert np.array_equal(new.x, old.x) and np.array_equal(new.diam, old.diam)
    assert new.meta.keys() == old.meta.keys() and new.meta["source"] == old.meta["source"]
    if old.meta["species"] is None:
        assert new.meta["species"] is None
    else:
        assert new.meta["species"].dtype == old.meta["species"].dtype
        assert np.array_equal(new.meta["species"], old.meta["species"])
    a, b = active.row_block(whole.n, COMM)  # each rank holds its own block only
    assert (new.lo, len(new.x)) == (a, b - a)


def test_coinciding_centres_are_refused_as_read_packing_does(shared_tmp):
    """Two particles at one place (on different ranks' rows, across a periodic boundary): the
    one-line error of read_packing, found on the slabs."""
    p = random_packing(3, 40, 0.3, rng=np.random.default_rng(7))
    pos = p.pos.copy()
    pos[35] = pos[2] + np.array([p.L, 0.0, -p.L])  # the same centre, one box away
    path = write_start(os.path.join(shared_tmp, "from-dup.h5"), pos, p.diam, p.L)
    with pytest.raises(ParjamError) as exc:
        h5md.read_packing(path)
    assert "particles 2 and 35 coincide (1 duplicated pair(s))" in str(exc.value)
    with pytest.raises(ParjamError) as got:
        filestart.describe(COMM, rowio.read_rows(COMM, path))
    assert str(got.value) == str(exc.value)


def run(argv):
    """(status, stderr) of an in-process ``parjam`` call."""
    err = pyio.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(pyio.StringIO()):
        rc = cli.main(list(argv))
    return rc, err.getvalue()


def assert_same_files(a, b, exact):
    names = sorted(n for n in os.listdir(a) if n.endswith(".h5"))
    assert names == sorted(n for n in os.listdir(b) if n.endswith(".h5")) and names
    for name in names:
        if exact:
            assert differences(os.path.join(a, name), os.path.join(b, name)) == [], name
        else:
            with h5py.File(os.path.join(a, name)) as fa, h5py.File(os.path.join(b, name)) as fb:
                assert_same_member(fa, fb, name)


def test_pack_from_makes_the_files_of_the_whole_file_start(starts, shared_tmp, monkeypatch):
    """The protocol from the rows against the protocol from main's whole-file start (the
    Jammer built from importer.from_file on every rank): bitwise on one rank; on 2 the member
    is shared, and two shared runs agree to round-off only (their MUMPS factorisations)."""
    new, old = os.path.join(shared_tmp, "from-new"), os.path.join(shared_tmp, "from-old")
    assert cli.main(["pack", "--from", starts["bi"], "--out", new, *PROTOCOL]) == 0
    monkeypatch.setattr(members.filestart, "start_rows",
                        lambda comm, rows, alpha, phi: importer.from_file(rows.path, alpha))
    assert cli.main(["pack", "--from", starts["bi"], "--out", old, *PROTOCOL]) == 0
    assert_same_files(new, old, exact=COMM.Get_size() == 1)
    with h5py.File(os.path.join(new, "member0000_dphi1.0e-03.h5")) as f:
        assert f["parameters"].attrs["dispersity"] == "bi"
        assert np.array_equal(f["particles/all/species"][()],
                              h5md.read_packing(starts["bi"]).meta["species"])


@pytest.mark.serial
def test_pack_from_gives_the_same_files_on_one_two_and_three_ranks(starts, tmp_path):
    """One rank in this process, 2 and 3 by mpirun (3: a middle rank, 43 rows split 15/14/14):
    the same minima, to a shared member's round-off."""
    one = str(tmp_path / "one")
    assert cli.main(["pack", "--from", starts["poly"], "--out", one, *PROTOCOL]) == 0
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    for ranks in (2, 3):
        out = str(tmp_path / f"on{ranks}")
        r = subprocess.run(mpirun + ["-n", str(ranks), sys.executable, "-m", "parjam", "pack",
                                     "--from", starts["poly"], "--out", out, *PROTOCOL],
                           env=subprocess_env(), capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        assert_same_files(out, one, exact=False)


@pytest.mark.serial
def test_rows_on_three_ranks():
    """The row tests of this file on 3 ranks (uneven blocks, a middle rank)."""
    res = run_on_ranks("test_pack_from.py", 3, "-k", "whole_files or coinciding")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


def test_bad_start_is_one_line_and_exit_2_before_any_work(shared_tmp, monkeypatch):
    """A missing file, positions of d = 4, a reference spectrum (.npz) instead of a packing,
    coinciding centres: one line, exit 2, no output directory, no member started.  (parjam's
    own HDF5 spectrum file carries its packing's particles, by design, and is a valid start, on
    main as here.)"""
    def forbidden(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(members, "pack_member", forbidden)
    p = random_packing(3, 40, 0.3, rng=np.random.default_rng(7))
    wide = write_start(os.path.join(shared_tmp, "from-d4.h5"), np.tile(p.pos, (1, 2))[:, :4],
                       p.diam, p.L)
    cases = {"no such file": os.path.join(shared_tmp, "absent.h5"),
             "positions must have shape (N, 2) or (N, 3)": wide,
             "not an HDF5 file": REF.replace(".h5", ".spectrum.npz"),
             "coincide": write_start(os.path.join(shared_tmp, "from-dup2.h5"),
                                     np.concatenate([p.pos, p.pos[:1]]),
                                     np.concatenate([p.diam, p.diam[:1]]), p.L)}
    for what, path in cases.items():
        out = os.path.join(shared_tmp, "from-bad-out")
        rc, err = run(["pack", "--from", path, "--out", out, *PROTOCOL])
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        assert rc == 2, (what, err)
        if COMM.Get_rank() == 0:
            assert len(lines) == 1 and lines[0].startswith("parjam: error: "), (what, err)
            assert what in lines[0] and path in lines[0], (what, err)
        assert not os.path.exists(out), what


def test_start_from_file_reads_only_its_rows(starts, monkeypatch):
    """The command's description of the file (pack.start_from_file) reads no whole dataset:
    every read of the position and diameter datasets is this rank's block of rows."""
    sizes = []
    real = h5py.Dataset.__getitem__

    def spy(self, key):
        value = real(self, key)
        if self.name.endswith(("position/value", "diameter")):
            sizes.append(np.asarray(value).reshape(-1, self.shape[-1] if self.ndim > 1 else 1)
                         .shape[0])
        return value

    monkeypatch.setattr(h5py.Dataset, "__getitem__", spy)

    class Args:
        start, members = starts["poly"], 1

    pack_cmd.start_from_file(Args)
    assert Args.n == 43 and Args.dispersity == "poly" and sizes
    a, b = active.row_block(43, COMM)
    assert max(sizes) == b - a
