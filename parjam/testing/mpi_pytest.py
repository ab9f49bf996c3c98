"""Run pytest on every MPI rank: ``mpirun -n 2 python -m parjam.testing.mpi_pytest [args]``.

Rank 0 reports; the other ranks run silently.  The exit status is the largest over the ranks, so
a failure on any rank fails the run.  Tests marked ``serial`` (they start their own processes)
are deselected here, since they already run in the serial pass.
"""

import os
import sys


def main():
    from mpi4py import MPI

    import pytest

    comm = MPI.COMM_WORLD
    args = list(sys.argv[1:]) + ["-m", "not serial"]
    if comm.Get_rank() != 0:
        devnull = open(os.devnull, "w")
        os.dup2(devnull.fileno(), 1)
        args += ["-q"]
    rc = int(pytest.main(args))
    worst = comm.allreduce(rc, op=MPI.MAX)
    sys.stdout.flush()
    return worst


if __name__ == "__main__":
    sys.exit(main())
