"""Run pytest on every MPI rank: ``mpirun -n 2 python -m parjam.testing.mpi_pytest [args]``.

Rank 0 reports; the other ranks run silently.  The exit status is the largest over the ranks, so
a failure on any rank fails the run.  Tests marked ``serial`` (they start their own processes)
are deselected here, since they already run in the serial pass.

A test that fails on some ranks only is the dangerous case: the ranks that failed leave the test
early, while the others may still wait in one of its collective calls, so the next collective
deadlocks.  After every test the ranks therefore compare outcomes on a private communicator:

- every rank reached the check: a failure on another rank is reported on rank 0 as a failed test
  (``failed on rank R`` with that rank's traceback), and all ranks go on with the next test;
- a rank that failed waits at most ``PARJAM_MPI_TEST_TIMEOUT`` seconds (default 120) for the
  others; if they do not arrive (stuck in a collective of the failed test) it prints which test
  failed where and calls MPI Abort, which ends the whole job at once instead of hanging;
- a rank that passed waits at most 4 such timeouts (a rank that failed may be stuck in a
  collective the others left, e.g. while hypothesis shrinks its failure), then aborts the same way.
"""

import os
import sys
import time

import pytest

DEFAULT_TIMEOUT = 120.0
PASSED_FACTOR = 4  # a rank that passed waits this many timeouts for the others before aborting


class CollectiveOutcome:
    """pytest plugin: per-test comparison of the outcomes of all ranks (see the module doc)."""

    def __init__(self, comm, timeout):
        self.comm = comm.Dup()  # private: never matches a collective of the tests themselves
        self.rank = comm.Get_rank()
        self.size = comm.Get_size()
        self.timeout = timeout
        self.failures = []

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        self.failures = []
        yield
        self.check(item)

    def pytest_runtest_logreport(self, report):
        if report.failed:
            self.failures.append(f"[{report.when}] {report.longreprtext}")

    def check(self, item):
        import numpy as np

        mine = np.array([1 if self.failures else 0], dtype=np.int32)
        flags = np.zeros(self.size, dtype=np.int32)
        req = self.comm.Iallgather(mine, flags)
        start = time.monotonic()
        while not req.Test():
            waited = time.monotonic() - start
            if mine[0] and waited > self.timeout:
                self._abort(item, f"failed on rank {self.rank} and the other ranks did not "
                            f"finish it within {self.timeout:g} s (stuck in one of its "
                            f"collectives?)", self.failures[0])
            if waited > PASSED_FACTOR * self.timeout:  # e.g. another rank failed and is stuck
                self._abort(item, f"finished on rank {self.rank}, but the other ranks did not "
                            f"finish it within {PASSED_FACTOR * self.timeout:g} s (one of them "
                            f"stuck after a failure of its own?)", "")
            time.sleep(0.002)
        if not flags.any():
            return
        texts = self.comm.gather("\n".join(self.failures) if mine[0] else None, root=0)
        if self.rank != 0:
            return
        for r in range(1, self.size):
            if flags[r]:
                self._report(item, f"failed on rank {r} (rank 0: "
                             f"{'failed too' if flags[0] else 'passed'}):\n{texts[r]}")

    @staticmethod
    def _abort(item, why, detail):
        from mpi4py import MPI

        sys.stderr.write(f"mpi_pytest: {item.nodeid} {why}: aborting every rank.\n{detail}\n")
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(1)

    @staticmethod
    def _report(item, text):
        from _pytest.reports import TestReport

        rep = TestReport(item.nodeid, item.location, keywords={}, outcome="failed",
                         longrepr=text, when="call", sections=[], duration=0.0)
        item.ihook.pytest_runtest_logreport(report=rep)


def main():
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    args = list(sys.argv[1:]) + ["-m", "not serial"]
    if comm.Get_rank() != 0:
        devnull = open(os.devnull, "w")
        os.dup2(devnull.fileno(), 1)
        args += ["-q"]
    timeout = float(os.environ.get("PARJAM_MPI_TEST_TIMEOUT", DEFAULT_TIMEOUT))
    rc = int(pytest.main(args, plugins=[CollectiveOutcome(comm, timeout)]))
    worst = comm.allreduce(rc, op=MPI.MAX)
    sys.stdout.flush()
    return worst


if __name__ == "__main__":
    sys.exit(main())
