"""Peak resident set per rank of one command on P MPI ranks (/usr/bin/time's %M on every
rank), for the memory benchmarks of scripts/ (run by hand, never in the test suite)."""

import os
import re
import shlex
import subprocess
import sys
import time


def mpirun():
    """$PARJAM_MPIRUN split (scripts/mpi-env), else an oversubscribing mpirun."""
    return shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))


def measured(ranks, argv, what=None, env=None, cwd=None):
    """Run ``argv`` on ``ranks`` ranks, one OpenMP thread each (``env``: more variables, e.g.
    PYTHONPATH of the code under test; ``cwd``: where): (peak RSS per rank in MB, seconds,
    CompletedProcess).  No memory report (the run never started) ends the benchmark with the
    run's output and one line naming ``what`` (default the command)."""
    cmd = mpirun() + ["-n", str(ranks), "/usr/bin/time", "-f", "PEAKRSS %M"] + list(argv)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd,
                         env=dict(os.environ, OMP_NUM_THREADS="1", **(env or {})))
    secs = time.perf_counter() - t0
    mb = [int(m) / 1024.0 for m in re.findall(r"PEAKRSS (\d+)", res.stderr)]
    if not mb:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{what or ' '.join(argv)}: no memory report")
    return mb, secs, res
