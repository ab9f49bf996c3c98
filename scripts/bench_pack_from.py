#!/usr/bin/env python3
"""Peak memory per rank of the start of ``parjam pack --from FILE`` (issue 18, session 14): main's
whole-file start (OLD: ``io.read_packing`` of all N particles on every rank to describe the file,
then ``importer.from_file`` of all N on every rank and ``Jammer(comm, pack)``) against the start
by rows (NEW: ``parjam.pack.filestart.describe`` and ``filestart.start_rows``, each rank reading only
its block of rows, then ``Jammer(comm, rows)``), side by side in one run, at P = 1, 2, 4 ranks
(oversubscribed on a small machine: that changes the times, not the memory).  Run by hand,
never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/tile_packing.py tests/data/ref_d3_mono_N128_dphi1e-03.h5 10 BIG.h5
    .venv/bin/python scripts/bench_pack_from.py BIG.h5 --ranks 1 2 4

Both variants are this tree's code: OLD calls the functions main's ``pack --from`` called
(read_packing and importer.from_file are unchanged), so the rest of the command is the same
code in both.  Each point is ``mpirun -n P /usr/bin/time python -c WORKER`` (peak_rss.measured);
the worker does what ``pack --from`` does before its first minimisation (describe the file,
read the member's start, build the Jammer) and reports each rank's peak after its imports and at
the end; the table gives the largest rank's whole peak (/usr/bin/time) and what the start added
to the peak after the imports.  The Jammer's block rows of OLD and NEW are checked to be the
same bitwise (a hash per rank).
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
from types import SimpleNamespace
from parjam import env
from parjam.pack.packing import Jammer
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
mb = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
path, variant = sys.argv[1], sys.argv[2]
before = mb()
t0 = time.perf_counter()
if variant == "old":  # main's pack --from: the whole file on every rank, twice
    from parjam.files.importer import from_file
    from parjam.files.h5md import read_packing
    whole = read_packing(path)
    phi = whole.phi
    del whole
    start = from_file(path, 2.0)
else:
    from parjam.pack import filestart
    phi = filestart.describe(comm, path).phi
    start = filestart.start_rows(comm, path, 2.0, phi)
jam = Jammer(comm, start)
del start
secs = time.perf_counter() - t0
after = mb()
x = jam.ff.local(jam.ff.x)
digest = hashlib.sha256(x.tobytes() + jam.ff.diam_rows.tobytes()).hexdigest()[:16]
got = comm.tompi4py().gather((before, after, secs, digest), root=0)
if comm.getRank() == 0:
    print("RESULT", json.dumps({"before": max(g[0] for g in got),
                                "after": max(g[1] for g in got),
                                "added": max(g[1] - g[0] for g in got),
                                "seconds": max(g[2] for g in got),
                                "digests": [g[3] for g in got], "phi": phi, "n": jam.n}))
jam.destroy()
"""


def point(path, ranks, variant):
    mb, secs, res = measured(ranks, [sys.executable, "-c", WORKER, path, variant],
                             f"{variant} on {ranks} rank(s)",
                             env={"PYTHONPATH": ROOT, "OPENBLAS_NUM_THREADS": "1"})
    found = re.search(r"^RESULT (.*)$", res.stdout, re.M)
    if res.returncode != 0 or not found:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{variant} on {ranks} rank(s) failed")
    return dict(json.loads(found.group(1)), peak=max(mb), ranks=ranks, wall=secs)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("packing", help="the start file (e.g. a tiled packing)")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--out", default=None, help="markdown table (default stdout)")
    a = ap.parse_args()
    rows = []
    for p in a.ranks:
        old, new = point(a.packing, p, "old"), point(a.packing, p, "new")
        if old["digests"] != new["digests"] or old["phi"] != new["phi"]:
            raise SystemExit(f"P = {p}: the start by rows differs from the whole-file start")
        rows.append((p, old, new))
        print(f"P = {p}: old peak {old['peak']:.0f} MB (start +{old['added']:.1f}), new "
              f"{new['peak']:.0f} MB (+{new['added']:.1f})", file=sys.stderr, flush=True)
    n = rows[0][1]["n"]
    out = [f"`pack --from` start at N = {n:,} ({os.path.basename(a.packing)}), peak RSS of the "
           "largest rank (MB); 'start' is what describing the file, reading the start and "
           "building the Jammer added to the peak after the imports; the Jammer's rows of old "
           "and new are bitwise the same on every rank.", "",
           "| P | peak old | peak new | new / old | start old | start new | start new / old "
           "| s old | s new |", "|---|---|---|---|---|---|---|---|---|"]
    for p, old, new in rows:
        out.append(f"| {p} | {old['peak']:.0f} | {new['peak']:.0f} | "
                   f"{new['peak'] / old['peak']:.2f} | {old['added']:.1f} | {new['added']:.1f} | "
                   f"{new['added'] / max(old['added'], 1e-9):.2f} | {old['seconds']:.2f} | "
                   f"{new['seconds']:.2f} |")
    text = "\n".join(out) + "\n"
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
    sys.stdout.write(text)


if __name__ == "__main__":
    main()
