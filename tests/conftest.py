"""Shared fixtures.  Tests run serially and under ``mpirun -n 2`` (parjam.testing.mpi_pytest)."""

import os
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
