"""Shared fixtures.  Tests run serially and under ``mpirun -n 2`` (parjam.testing.mpi_pytest)."""

import os
import subprocess
import sys
import tempfile

import pytest

from parjam import env

env.init()


@pytest.fixture(scope="session")
def world():
    """PETSc's COMM_WORLD (2 ranks under the MPI pass)."""
    return env.petsc().COMM_WORLD


@pytest.fixture(scope="session")
def shared_tmp():
    """A temporary directory that every rank sees (rank 0 creates it, the others are told)."""
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    path = tempfile.mkdtemp(prefix="parjam-test-") if comm.Get_rank() == 0 else None
    path = comm.bcast(path, root=0)
    yield path
    comm.Barrier()
    if comm.Get_rank() == 0:
        import shutil

        shutil.rmtree(path, ignore_errors=True)


DATA = os.path.join(os.path.dirname(__file__), "data")


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def subprocess_env(**extra):
    """Environment for a parjam subprocess (serial or mpirun): this checkout on the path, Open MPI
    allowed as root and oversubscribed, one BLAS thread, no inherited PARJAM_FAULT."""
    env = dict(os.environ, PYTHONPATH=ROOT, OMPI_ALLOW_RUN_AS_ROOT="1",
               OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1",
               OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", OMPI_MCA_mpi_yield_when_idle="1")
    env.pop("PARJAM_FAULT", None)
    env.update(extra)
    return env


def find_test(test_file):
    """The path of a test file of tests/ given by its name (test files are in one folder per
    package, and their names are unique)."""
    import glob

    found = glob.glob(os.path.join(ROOT, "tests", "**", test_file), recursive=True)
    if len(found) != 1:
        raise FileNotFoundError(f"{test_file}: {len(found)} test files of that name in tests/")
    return found[0]


def run_on_ranks(test_file, ranks, *pytest_args, timeout=600):
    """Run a test file of tests/ under ``$PARJAM_MPIRUN -n ranks`` (for the partition cases the
    2-rank suite cannot make); returns the CompletedProcess, output captured."""
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    return subprocess.run(mpirun + ["-n", str(ranks), sys.executable, "-m",
                                    "parjam.testing.mpi_pytest", "-q", "-p", "no:cacheprovider",
                                    *pytest_args, find_test(test_file)],
                          cwd=ROOT, env=subprocess_env(), capture_output=True, text=True,
                          timeout=timeout)


# Tests write only inside temporary directories of their own: anything new in the checkout's top
# folder (or the folder pytest runs in) after the session fails the run, naming it.
def listing():
    return {os.path.join(folder, name) for folder in {ROOT, os.getcwd()}
            for name in os.listdir(folder) if not name.startswith(".") and name != "__pycache__"}


BEFORE = listing()


def pytest_sessionfinish(session, exitstatus):
    stray = sorted(listing() - BEFORE)
    if stray:
        sys.stderr.write(f"\ntests wrote outside their temporary directories: {stray}\n")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
