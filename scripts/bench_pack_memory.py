#!/usr/bin/env python3
"""Peak memory per rank of ``parjam pack`` for one member shared by P ranks (issue 18: the
Jammer on the domain decomposition), the code of main (OLD: an extracted checkout, e.g.
``git archive main | tar -x -C /tmp/jam-old``) and of this tree (NEW) side by side in one run.
Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_pack_memory.py --old /tmp/jam-old \
        --per-rank 25000 --ranks 1 2 4 --out docs/bench-pack-memory.md

Each point is ``mpirun -n P /usr/bin/time python -m parjam pack --dim 3 --n (per-rank x P)
--phic-method extrapolate --dphi DPHI`` with this tree's interpreter and the tree's code on
PYTHONPATH (the old and the new runs of a point follow each other); /usr/bin/time reports the
peak resident set size (max RSS) of each rank, the table gives the largest over the ranks, the
ratio NEW / OLD and the wall times.  Both versions write the same files (the seed is fixed; on
one rank they are bit-identical), in temporary directories that are removed.  Ranks are
oversubscribed on a small machine, which changes the times, not the memory.

``--states SMALL.h5:K ...`` adds the second table: the Jammer's per-state steps alone (what
issue 18 moved onto the slabs) at ~25,000 particles per rank, where a whole ``pack`` would take
hours here: the jammed packing SMALL tiled K^d times (scripts/tile_packing.py's ``tiled``,
in memory), a Jammer on it, then the state's network, the active Hessian and its distributed
matrix (old: ``network.analyze`` of the whole packing on every rank and the replicated contact
blocks; new: ``Jammer.network`` and the half-edges).  Peak RSS per rank before those steps
(the Jammer built) and after them; the increment is what the steps add.
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PY = os.path.join(ROOT, ".venv", "bin", "python")
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from peak_rss import measured, mpirun  # noqa: E402


def peak_rss(tree, ranks, n, dphi, seed, out):
    """(largest peak RSS over the ranks in MB, wall seconds, exit code) of one pack run."""
    argv = [PY, "-m", "parjam", "pack", "--dim", "3", "--n", str(n), "--phic-method",
            "extrapolate", "--dphi", str(dphi), "--seed", str(seed), "--checkpoint-every", "0",
            "--force", "-q", "--out", out]
    mb, secs, res = measured(ranks, argv, tree, env={"PYTHONPATH": tree,
                                                     "OPENBLAS_NUM_THREADS": "1"},
                             cwd=tempfile.gettempdir())
    return max(mb), secs, res.returncode


WORKER = """
import json, resource, sys
from parjam import env; from parjam.pack import stability  # the tree on PYTHONPATH, before tile_packing's path
from parjam.files.h5md import read_packing
from parjam.pack.packing import Jammer
sys.path.insert(0, sys.argv[3])
from tile_packing import tiled
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
pack = tiled(read_packing(sys.argv[1]), int(sys.argv[2]))
jam = Jammer(comm, pack)
del pack
mb = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
before = mb()
if hasattr(jam, "network"):  # this tree: on the slabs
    net = jam.network()
    H = stability.active_hessian(net)
else:  # main: the whole packing analysed on every rank
    from parjam.net.network import analyze
    net = analyze(jam.pack)
    H = stability.active_hessian(jam.pack, net)
A = H.matrix(comm)
A.destroy()
after = mb()
got = comm.tompi4py().gather((before, after), root=0)
if comm.getRank() == 0:
    print("RESULT", json.dumps({"n": jam.ff.n, "before": max(g[0] for g in got),
                                "after": max(g[1] for g in got),
                                "added": max(g[1] - g[0] for g in got)}))
"""


def state_steps(tree, ranks, small, k):
    """{n, before, after, added} (MB, largest rank) of the per-state steps (module doc)."""
    cmd = mpirun() + ["-n", str(ranks), PY, "-c", WORKER, small, str(k),
                      os.path.join(ROOT, "scripts")]
    env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    found = re.search(r"RESULT (.*)", res.stdout)
    if not found:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{tree}: no result")
    return json.loads(found.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="directory of main's extracted checkout")
    ap.add_argument("--per-rank", type=int, default=25000, help="particles per rank")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--dphi", type=float, default=1e-2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-pack-memory.md"))
    ap.add_argument("--states", nargs="*", default=[], metavar="P:SMALL.h5:K",
                    help="points of the per-state table (module doc)")
    args = ap.parse_args()
    work = tempfile.mkdtemp(prefix="parjam-bench-pack-mem-")
    rows, steps = [], []
    for spec in args.states:
        ranks, small, k = spec.split(":")
        got = {label: state_steps(tree, int(ranks), os.path.abspath(small), int(k))
               for label, tree in (("old", os.path.abspath(args.old)), ("new", ROOT))}
        steps.append((int(ranks), got["old"], got["new"]))
        print(f"states P={ranks} N={got['new']['n']}: old +{got['old']['added']:.0f} MB "
              f"(peak {got['old']['after']:.0f}), new +{got['new']['added']:.0f} MB (peak "
              f"{got['new']['after']:.0f})", flush=True)
    try:
        for ranks in args.ranks:
            n = args.per_rank * ranks
            got = {}
            for label, tree in (("old", os.path.abspath(args.old)), ("new", ROOT)):
                out = os.path.join(work, f"{label}{ranks}")
                got[label] = peak_rss(tree, ranks, n, args.dphi, args.seed, out)
                shutil.rmtree(out, ignore_errors=True)
            rows.append((ranks, n, got["old"], got["new"]))
            print(f"P={ranks} N={n}: old {got['old'][0]:.0f} MB ({got['old'][1]:.0f} s, rc "
                  f"{got['old'][2]}), new {got['new'][0]:.0f} MB ({got['new'][1]:.0f} s, rc "
                  f"{got['new'][2]})", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write(args.out, rows, steps, args)


def write(path, rows, steps, args):
    lines = ["# Peak memory per rank of `parjam pack`, one member shared by P ranks (issue 18)",
             "",
             "Written by `scripts/bench_pack_memory.py` (old = main's code, new = this tree, in "
             f"one run; 3D monodisperse, {args.per_rank} particles per rank, `--phic-method "
             f"extrapolate --dphi {args.dphi:g} --seed {args.seed}`; peak RSS per rank from "
             "/usr/bin/time, the largest over the ranks; ranks oversubscribed on a 2-core "
             "machine shared with other jobs, which changes the times, not the memory).", "",
             "| P | N | old MB/rank | new MB/rank | new/old | old s | new s |",
             "|---|---|---|---|---|---|---|"]
    for ranks, n, old, new in rows:
        flag = "" if old[2] == 0 and new[2] == 0 else f" (exit {old[2]}/{new[2]})"
        lines.append(f"| {ranks}{flag} | {n} | {old[0]:.0f} | {new[0]:.0f} | "
                     f"{new[0] / old[0]:.2f} | {old[1]:.0f} | {new[1]:.0f} |")
    if steps:
        lines += ["", "The per-state steps alone (network, active Hessian, its matrix; module doc "
                  "of the script): peak RSS per rank in MB, the largest rank, before them and "
                  "after, and the increment.", "",
                  "| P | N | N/P | old before | old after | old added | new before | new after "
                  "| new added |", "|---|---|---|---|---|---|---|---|---|"]
        for ranks, old, new in steps:
            lines.append(f"| {ranks} | {new['n']} | {new['n'] // ranks} | {old['before']:.0f} | "
                         f"{old['after']:.0f} | {old['added']:.0f} | {new['before']:.0f} | "
                         f"{new['after']:.0f} | {new['added']:.0f} |")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
