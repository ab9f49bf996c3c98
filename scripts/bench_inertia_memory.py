#!/usr/bin/env python3
"""Peak memory of the packing protocol's stability check (parjam.pack.stability.check: the inertia of
the MUMPS LDL^T of the full Hessian of the non-rattlers) with the factor kept, as before, and
discarded as it is computed (MUMPS ICNTL(31) = 1, ``factor.exact_inertia(inertia_only=True)``,
now the default), side by side in one run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_inertia_memory.py [--tiles 2 3 4 5] [--ranks 1 2]
        [--out docs/bench-inertia-memory.md]

Packings: tests/data/soft_d3_N512_m0.h5 (3D, near jamming) tiled k x k x k times
(scripts/tile_packing.py) in a temporary directory.  Every (N, P, variant) is a fresh process
(``kept`` runs with -stability_mat_mumps_icntl_31 0, which the prefix lets a user give), so its
peak resident set (getrusage ru_maxrss, largest rank) is that of one check; ``before`` is the
resident set once the network is built.  The negative-curvature counts must agree.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHON = os.path.join(ROOT, ".venv", "bin", "python")
SMALL = os.path.join(ROOT, "tests", "data", "soft_d3_N512_m0.h5")
VARIANTS = {"kept": "-stability_mat_mumps_icntl_31 0", "discarded": ""}

CHILD = r"""
import json, resource, sys, time
from parjam import env; from parjam.files import h5md; from parjam.pack import jamnet, stability
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
mpi = comm.tompi4py()
def rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
pack = h5md.read_packing(sys.argv[1])
net = jamnet.from_packing(mpi, pack)
before = rss()
t0 = time.perf_counter()
cur = stability.check(comm, net)
sec = time.perf_counter() - t0
peak = rss()
rows = mpi.gather((before, peak))
if mpi.rank == 0:
    print("RESULT " + json.dumps({"n": pack.n, "n_active": net.n_active,
                                  "before": max(r[0] for r in rows),
                                  "peak": max(r[1] for r in rows), "seconds": sec,
                                  "negative": cur.n_negative}))
"""


def run(path, ranks, variant):
    env = dict(os.environ, PETSC_OPTIONS=VARIANTS[variant])
    cmd = [PYTHON, "-c", CHILD, path]
    if ranks > 1:
        cmd = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split() + \
            ["-n", str(ranks)] + cmd
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True).stdout
    return json.loads(next(line for line in out.splitlines()
                           if line.startswith("RESULT "))[7:])


def table(rows):
    lines = [
        "# Memory of the stability check: MUMPS factor kept or discarded (issue 18)",
        "",
        "Written by `scripts/bench_inertia_memory.py` (both variants in one run, each (N, P, "
        "variant) a fresh process; 3D packings tiled from tests/data/soft_d3_N512_m0.h5; peak "
        "RSS of the largest rank; `kept` = -stability_mat_mumps_icntl_31 0, the factor kept "
        "as before; `discarded` = ICNTL(31) = 1, the default now). `extra` = peak - the resident "
        "set once the network is built. Times are of a shared machine and only indicate.",
        "",
        "| N | dof | P | before MB | kept peak MB | discarded peak MB | extra, discarded / kept "
        "| kept s | discarded s | negative curvatures (kept, discarded) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (n, p), r in sorted(rows.items()):
        k, dsc = r["kept"], r["discarded"]
        ratio = (dsc["peak"] - dsc["before"]) / max(k["peak"] - k["before"], 1e-9)
        lines.append(f"| {n} | {3 * k['n_active']} | {p} | {k['before']:.0f} | {k['peak']:.0f} | "
                     f"{dsc['peak']:.0f} | {ratio:.2f} | {k['seconds']:.1f} | "
                     f"{dsc['seconds']:.1f} | {k['negative']}, {dsc['negative']} |")
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", type=int, nargs="+", default=[2, 3, 4, 5])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-inertia-memory.md"))
    args = ap.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory(prefix="parjam-inertia-") as tmp:
        for k in args.tiles:
            path = os.path.join(tmp, f"t{k}.h5")
            subprocess.run([PYTHON, os.path.join(ROOT, "scripts", "tile_packing.py"), SMALL,
                            str(k), path], check=True, capture_output=True)
            for p in args.ranks:
                got = {v: run(path, p, v) for v in VARIANTS}
                rows[(got["kept"]["n"], p)] = got
                print(f"N = {got['kept']['n']}, P = {p}: " + ", ".join(
                    f"{v} {r['peak']:.0f} MB {r['seconds']:.1f} s ({r['negative']})"
                    for v, r in got.items()), flush=True)
    bad = [key for key, r in rows.items() if r["kept"]["negative"] != r["discarded"]["negative"]]
    text = "\n".join(table(rows)) + "\n"
    if bad:
        text += f"\nCOUNTS DIFFER at (N, P) = {bad}\n"
    with open(args.out, "w") as fh:
        fh.write(text)
    print(text)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
