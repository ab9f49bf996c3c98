#!/usr/bin/env python3
"""Peak memory per rank of the random start and the Jammer's construction for one member shared
by P ranks (issue 18, session 13): main's code (OLD: ``random_packing`` of all N particles on
every rank, then ``Jammer(comm, pack)``) and this tree's (NEW: ``randomstart.start_rows``, each
rank's block rows only, then ``Jammer(comm, rows)``) side by side in one run, at a fixed number
of particles per rank.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_random_start.py --old /work/main \\
        --per-rank 25000 --ranks 1 2 4 8 --out docs/bench-random-start.md

Each point is ``mpirun -n P /usr/bin/time python -c WORKER`` (scripts/peak_rss.py's
``measured``) with the tree's own interpreter (its .venv) and its code on PYTHONPATH; the old
and the new run of a point follow each other.  /usr/bin/time gives each rank's peak resident
set; the worker also reports each rank's peak after its imports (PETSc, numpy: the same for
both) and at the end, so the table gives the largest rank's whole peak and what the start and
the construction added to it.  The new start is checked against the old on the same seed: the
worker hashes the gathered positions of the Jammer (a gather made after the peak is read).
Ranks are oversubscribed on a small machine, which changes the times, not the memory.
"""

import argparse
import json
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from peak_rss import measured  # noqa: E402

WORKER = """
import hashlib, json, resource, sys, time
from parjam import env
from parjam.pack.packing import Jammer
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
mb = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
n, seed = int(sys.argv[1]), int(sys.argv[2])
args = (3, n, 0.66, 2.0, "poly", 1.4)
before = mb()
t0 = time.perf_counter()
try:  # this tree: the block rows of the start
    from parjam.pack.randomstart import member_rng, start_rows
except ImportError:  # main: the whole start on every rank
    from parjam.pack.packing import member_rng, random_packing
    start = random_packing(*args, rng=member_rng(seed, 0))
else:
    start = start_rows(comm, *args, rng=member_rng(seed, 0))
jam = Jammer(comm, start)
del start
secs = time.perf_counter() - t0
after = mb()
got = comm.tompi4py().gather((before, after, secs), root=0)
try:  # after the peak is read: the check of old == new
    from parjam.testing.gather import gather
except ImportError:  # main before the gathers left ForceField
    pos = jam.ff.gather()
else:
    pos = gather(jam.ff)
if comm.getRank() == 0:
    print("RESULT", json.dumps({"before": max(g[0] for g in got),
                                "after": max(g[1] for g in got),
                                "added": max(g[1] - g[0] for g in got),
                                "seconds": max(g[2] for g in got),
                                "L": jam.L, "hash": hashlib.sha1(pos.tobytes()).hexdigest()}))
jam.destroy()
"""


def point(tree, ranks, n, seed):
    """The worker's RESULT and the largest /usr/bin/time peak over the ranks (MB)."""
    python = os.path.join(tree, ".venv", "bin", "python")
    mb, secs, res = measured(ranks, [python, "-c", WORKER, str(n), str(seed)], tree,
                             env={"PYTHONPATH": tree, "OPENBLAS_NUM_THREADS": "1"},
                             cwd=tree)
    found = re.search(r"RESULT (.*)", res.stdout)
    if res.returncode != 0 or not found:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{tree} on {ranks} ranks: no result")
    return dict(json.loads(found.group(1)), peak=max(mb), wall=secs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="main's checkout (with its .venv), read only")
    ap.add_argument("--per-rank", type=int, default=25000, help="particles per rank")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-random-start.md"))
    args = ap.parse_args()
    rows = []
    for ranks in args.ranks:
        n = args.per_rank * ranks
        old = point(os.path.abspath(args.old), ranks, n, args.seed)
        new = point(ROOT, ranks, n, args.seed)
        same = old["hash"] == new["hash"] and old["L"] == new["L"]
        rows.append((ranks, n, old, new, same))
        print(f"P={ranks} N={n}: old peak {old['peak']:.0f} MB (+{old['added']:.1f}), new "
              f"peak {new['peak']:.0f} MB (+{new['added']:.1f}), same start: {same}", flush=True)
    write(args.out, rows, args)


def write(path, rows, args):
    lines = ["# Peak memory per rank of the random start, one member shared by P ranks "
             "(issue 18, session 13)", "",
             "Written by `scripts/bench_random_start.py` (old = main's code with its .venv, new = "
             f"this tree, in one run; 3D polydisperse start at phi = 0.66, {args.per_rank} "
             f"particles per rank, seed {args.seed}; the random start and `Jammer` construction "
             "only).  *peak*: /usr/bin/time's peak RSS, the largest rank; *added*: that rank's "
             "peak at the end minus its peak after the imports (PETSc, numpy), i.e. what the "
             "start and the construction cost.  Ranks oversubscribed on a 2-core machine shared "
             "with other jobs (times are indicative only).  *same*: the Jammer's positions "
             "(gathered after the measurement) and box are bitwise the old ones.", "",
             "| P | N | old peak MB | new peak MB | old added MB | new added MB | new/old added "
             "| old s | new s | same |", "|---|---|---|---|---|---|---|---|---|---|"]
    for ranks, n, old, new, same in rows:
        ratio = new["added"] / old["added"] if old["added"] > 0 else float("nan")
        lines.append(f"| {ranks} | {n} | {old['peak']:.0f} | {new['peak']:.0f} | "
                     f"{old['added']:.1f} | {new['added']:.1f} | {ratio:.2f} | "
                     f"{old['seconds']:.2f} | {new['seconds']:.2f} | {'yes' if same else 'NO'} |")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
