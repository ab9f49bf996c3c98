"""Determinism: the same seed and options give the same files on 1 and 2 ranks (members spread
over ranks: every dataset bitwise, parameters too, only provenance and wall-clock times differ),
the same spectra on one rank and on all ranks to round-off (shift-and-invert and slicing), and
the same files when a command is run twice.  Resumed against uninterrupted runs: tests/hostile/test_resume.py."""

import glob
import os
import subprocess
import sys

import numpy as np
import pytest

from parjam import cli, env
from parjam.vib import spectrum
from parjam.files.h5md import read_packing
from parjam.testing.h5compare import differences
from conftest import ROOT

PETSc = env.petsc()
REF = os.path.join(ROOT, "tests", "data", "ref_d3_mono_N128_dphi1e-03.h5")


def _pack(out, args, mpi=0):
    env_ = dict(os.environ, PYTHONPATH=ROOT, OMPI_ALLOW_RUN_AS_ROOT="1",
                OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1",
                OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", OMPI_MCA_mpi_yield_when_idle="1")
    env_.pop("PARJAM_FAULT", None)
    cmd = [sys.executable, "-m", "parjam", "pack"] + args + ["--out", str(out), "-q"]
    if mpi:
        cmd = ["mpirun", "--oversubscribe", "-n", str(mpi)] + cmd
    r = subprocess.run(cmd, env=env_, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return sorted(glob.glob("*.h5", root_dir=out))


@pytest.mark.serial
@pytest.mark.parametrize("args", [
    ["--dim", "2", "--n", "32", "--dispersity", "bi", "--dphi", "1e-6", "1e-2",
     "--ladder", "decompress"],
    ["--dim", "3", "--n", "32", "--dphi", "1e-4"],
    ["--dim", "2", "--n", "32", "--dispersity", "poly", "--ratio", "2", "--pressure", "1e-3"],
])
def test_one_and_two_ranks_give_the_same_files(tmp_path, args):
    """Members spread over ranks (3 members on 2 ranks: 2 on rank 0, 1 on rank 1): every
    dataset and parameter of every file equal, bitwise."""
    args = args + ["--members", "3", "--seed", "21"]
    one = _pack(tmp_path / "one", args)
    two = _pack(tmp_path / "two", args, mpi=2)
    assert one == two and len(one) >= 6
    for name in one:
        assert differences(tmp_path / "one" / name, tmp_path / "two" / name) == [], name


def test_same_command_twice_gives_the_same_files(shared_tmp):
    """In-process, both passes: a second run into a fresh directory reproduces every dataset."""
    from mpi4py import MPI

    size = MPI.COMM_WORLD.Get_size()
    base = ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--dphi", "1e-4",
            "--seed", "8", "--members", str(max(2, size)), "-q", "--out"]
    a, b = os.path.join(shared_tmp, "det-a"), os.path.join(shared_tmp, "det-b")
    assert cli.main(base + [a]) == 0
    assert cli.main(base + [b]) == 0
    names = sorted(glob.glob("*.h5", root_dir=a))
    assert names == sorted(glob.glob("*.h5", root_dir=b)) and names
    for name in names:
        assert differences(os.path.join(a, name), os.path.join(b, name)) == []


@pytest.fixture(scope="module")
def pack():
    return read_packing(REF)


@pytest.mark.parametrize("method,request_", [("sinvert", {"k": 12}),
                                             ("slice", {"window": (0.05, 0.25)})])
def test_spectrum_on_one_rank_equals_all_ranks(pack, method, request_):
    """The distributed matrix and eigensolver on all ranks against one rank: eigenvalues to
    relative 1e-10, the same count (slicing: from the inertia), residuals below tolerance."""
    one = spectrum.compute(PETSc.COMM_SELF, spectrum.system_of(PETSc.COMM_SELF, pack), "full",
                           method=method, **request_)
    many = spectrum.compute(PETSc.COMM_WORLD, spectrum.system_of(PETSc.COMM_WORLD, pack),
                            "full", method=method, **request_)
    assert len(one.eigenvalue) == len(many.eigenvalue) == one.n_requested > 0
    assert np.allclose(one.eigenvalue, many.eigenvalue, rtol=1e-10, atol=1e-12 * one.norm)
    assert one.complete and many.complete
    assert many.error.max() <= many.tolerance
