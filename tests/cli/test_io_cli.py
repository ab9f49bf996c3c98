"""Files (H5MD layout, bitwise round trip, atomic writes), the command line and bad input."""

import glob
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parjam import cli
from parjam.errors import ParjamError
from parjam.files.h5md import observable, read_packing, write_packing
from parjam.net.network import analyze
from parjam.pack.packing import make_jammed
from conftest import ROOT

PARJAM = [sys.executable, "-m", "parjam"]


@pytest.fixture(scope="module")
def small_packing():
    phi_c, (pack,) = make_jammed(2, 64, [1e-3], seed=2)
    return pack


def test_round_trip_is_bitwise(tmp_path, small_packing):
    pack = small_packing
    net = analyze(pack)
    path = tmp_path / "p.h5"
    write_packing(path, pack, net, {"seed": 2, "protocol": "test"})
    back = read_packing(path)
    assert np.array_equal(back.pos, pack.pos)
    assert np.array_equal(back.diam, pack.diam)
    assert back.L == pack.L and back.alpha == pack.alpha
    net2 = analyze(back)
    assert net2.pressure == net.pressure and net2.n_contacts == net.n_contacts
    with h5py.File(path) as f:  # the H5MD layout, read with plain h5py
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert f["h5md/creator"].attrs["name"] == b"parjam"
        assert f["particles/all/position/value"].shape == (1, pack.n, 2)
        assert f["particles/all/position/step"][0] == 0
        assert f["particles/all/box"].attrs["dimension"] == 2
        assert f["connectivity/contacts"].shape == (len(net.all_contacts), 2)
        c = f["connectivity/contacts"][()]
        assert np.all(c[:, 0] < c[:, 1])
        assert observable(f, "pressure") == net.pressure
        assert observable(f, "excess") == net.excess
    assert not [p for p in os.listdir(tmp_path) if ".tmp" in p]


def test_reads_reference_layout_and_matches_its_numbers():
    import json

    ref = json.load(open(os.path.join(ROOT, "tests", "data", "reference.json")))
    for entry in ref:
        path = os.path.join(ROOT, "tests", "data", entry["file"])
        net = analyze(read_packing(path))
        assert net.n_active == entry["Nprime"]
        assert net.n_contacts == entry["Nc"] and net.n_iso == entry["Nc_iso"]
        assert net.pressure == pytest.approx(entry["pressure"], rel=1e-9)
        assert net.energy == pytest.approx(entry["energy"], rel=1e-9)
        assert net.max_force < 1e-13


def _corrupt(tmp_path, small_packing, name, mutate):
    path = tmp_path / f"{name}.h5"
    write_packing(path, small_packing, analyze(small_packing), {})
    with h5py.File(path, "a") as f:
        mutate(f)
    return path


def _replace(key, value):
    def mutate(f):
        del f[key]
        f[key] = value
    return mutate


BAD_FILES = {
    "nan": _replace("particles/all/position/value", np.full((1, 64, 2), np.nan)),
    "inf_diameter": _replace("particles/all/diameter", np.full(64, np.inf)),
    "shape": _replace("particles/all/position/value", np.zeros((1, 64, 4))),
    "diameter_length": _replace("particles/all/diameter", np.ones(10)),
    "negative_diameter": _replace("particles/all/diameter", -np.ones(64)),
    "zero_box": _replace("particles/all/box/edges", np.zeros(2)),
    "missing": lambda f: f.__delitem__("particles/all/diameter"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_files_are_rejected(tmp_path, small_packing, name):
    path = _corrupt(tmp_path, small_packing, name, BAD_FILES[name])
    with pytest.raises(ParjamError):
        read_packing(path)


def test_not_hdf5_and_truncated(tmp_path, small_packing):
    txt = tmp_path / "x.h5"
    txt.write_text("hello")
    with pytest.raises(ParjamError, match="not an HDF5"):
        read_packing(txt)
    good = tmp_path / "good.h5"
    write_packing(good, small_packing, analyze(small_packing), {})
    raw = good.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ParjamError):
        read_packing(cut)


def test_petsc_options_are_split_from_ours():
    ours, petsc = cli.split_petsc_args(
        ["pack", "--dphi", "1e-8", "-1e-3", "-log_view", "-eps_nev", "10", "-q",
         "-st_pc_type", "cholesky", "-eps_target", "-0.1", "--n", "64"])
    assert ours == ["pack", "--dphi", "1e-8", "-1e-3", "-q", "--n", "64"]
    assert petsc == ["-log_view", "-eps_nev", "10", "-st_pc_type", "cholesky",
                     "-eps_target", "-0.1"]


def _run(args, cwd, timeout=300, mpi=0):
    env = dict(os.environ, PYTHONPATH=ROOT)
    cmd = PARJAM + args
    if mpi:
        cmd = ["mpirun", "--oversubscribe", "-n", str(mpi)] + cmd
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


BAD_ARGS = [
    (["--dim", "4"], "--dim must be 2 or 3"),
    (["--n", "8"], "--n must be at least 16"),
    (["--alpha", "1.0"], "--alpha must be > 1"),
    (["--alpha", "nan"], "--alpha must be > 1"),
    (["--dispersity", "tri"], "unknown dispersity"),
    (["--phi", "-0.3"], "out of range"),
    (["--phi", "7"], "out of range"),
    (["--dphi", "0"], "--dphi values"),
    (["--phi", "0.40"], "unjammed"),
]


@pytest.mark.serial
@pytest.mark.parametrize("args,message", BAD_ARGS)
def test_bad_arguments_one_line_error_no_file(tmp_path, args, message):
    out = tmp_path / "out"
    r = _run(["pack", "--n", "64", "--out", str(out), "-q"] + args, tmp_path)
    assert r.returncode != 0
    lines = [ln for ln in r.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and message in lines[0], r.stderr
    assert not glob.glob(str(out / "*.h5"))


@pytest.mark.serial
def test_analyze_rejects_non_hdf5(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    r = _run(["analyze", str(bad)], tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip() == f"parjam: error: {bad}: not an HDF5 file"


@pytest.mark.serial
def test_same_packings_on_one_and_two_ranks_and_petsc_options(tmp_path):
    """Members spread over ranks give bitwise the same files' numbers as one rank; PETSc options
    given on the command line reach the solvers (-log_view prints its table)."""
    args = ["pack", "--dim", "2", "--n", "64", "--dispersity", "bi", "--members", "2",
            "--seed", "9", "--dphi", "1e-4", "-q"]
    r1 = _run(args + ["--out", "one"], tmp_path)
    r2 = _run(args + ["--out", "two", "-log_view"], tmp_path, mpi=2)
    assert r1.returncode == 0, r1.stderr
    assert r2.returncode == 0, r2.stderr
    assert "Performance Summary" in r2.stdout  # -log_view reached PETSc
    files = sorted(glob.glob("*.h5", root_dir=tmp_path / "one"))  # beside manifest.json
    assert files == sorted(glob.glob("*.h5", root_dir=tmp_path / "two")) and len(files) == 4
    for name in files:
        a, b = read_packing(tmp_path / "one" / name), read_packing(tmp_path / "two" / name)
        assert np.array_equal(a.pos, b.pos) and a.L == b.L
    with h5py.File(tmp_path / "two" / files[0]) as f:
        assert f["h5md/modules/parjam"].attrs["world_ranks"] == 2


@pytest.mark.serial
def test_failure_on_two_ranks_ends_both(tmp_path):
    """An unjammed member on each rank aborts the whole job promptly (no hang), no file."""
    r = _run(["pack", "--dim", "3", "--n", "64", "--members", "2", "--phi", "0.45",
              "--out", "o", "-q"], tmp_path, timeout=120, mpi=2)
    assert r.returncode != 0
    assert "unjammed" in r.stderr
    assert not glob.glob(str(tmp_path / "o" / "*.h5"))


@pytest.mark.serial
def test_info_reports_stack(tmp_path):
    r = _run(["info"], tmp_path)
    assert r.returncode == 0
    for key in ("parjam", "petsc", "slepc", "mpi", "ranks", "MUMPS"):
        assert key in r.stdout
