#!/usr/bin/env python3
"""Weak scaling of the peak memory per rank of ``parjam lengths`` on the distributed network
(issue 19): the l* cube counts, the structure factors and the sound speeds at a fixed number
of particles per rank, the code of main (OLD, another checkout's ``parjam``) and of this tree
(NEW) side by side in one run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_lengths_weak.py \
        --tiles 1:SMALL.h5:5 2:SMALL.h5:7 4:SMALL.h5:10 8:SMALL.h5:14 \
        --old /work/main/.venv/bin/parjam --out docs/bench-lengths-weak.md

Each ``--tiles P:SMALL:K`` is one point: the packing SMALL tiled K^d times
(scripts/tile_packing.py) run on P ranks.  The parts, each its own ``parjam lengths --what``:

- ``lstar``: cubes of fixed edges in units of the mean diameter (``--edges-sigma``, converted to
  the fractions of L that ``--edges`` takes), ``--samples`` positions each: the same cubes
  whatever P, so the per-rank memory shows what is replicated;
- ``structure``: the ``--k`` lowest modes (shift-and-invert, MUMPS) and F_L, F_T on the shells
  up to |m| = 4.5 (``--kmax`` = 4.5 x 2 pi / L);
- ``speeds``: B and G by linear response (parjam moduli's default solver);
- ``cubes``: the l* cubes at the command's default edges (0.2 .. 1 L, up to the whole packing),
  ``--samples`` positions each: main counts every cube on one rank, this tree counts a cube of
  more than N'/P members on all the ranks together (parjam.lengths.whole, issue 19 session 14).
  Not in the default ``--parts``: ``--parts cubes``.

``--old`` must import main's code: an executable of main's own venv, or a wrapper running
``python -P -m parjam`` with main's tree on PYTHONPATH (without ``-P``, ``-m`` puts the current
directory, this tree, ahead of PYTHONPATH and both columns measure the new code).

Every rank runs under /usr/bin/time (peak resident set size of that rank); the table gives the
largest and the mean over the ranks and the ratio NEW / OLD of the largest.  ``--parts`` and
``--max-ranks`` (per part) keep the run short.
"""

import argparse
import math
import os
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NEW = os.path.join(ROOT, ".venv", "bin", "parjam")
PY = os.path.join(ROOT, ".venv", "bin", "python")
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from peak_rss import measured  # noqa: E402
from tile_packing import weak_point  # noqa: E402
PARTS = ("lstar", "structure", "speeds", "cubes")
DEFAULT_PARTS = ("lstar", "structure", "speeds")


def peak_rss(exe, args, ranks):
    """(largest peak RSS over the ranks in MB, mean over the ranks, seconds, exit code)."""
    mb, secs, res = measured(ranks, [exe] + args)
    return max(mb), float(np.mean(mb)), secs, res.returncode


def box(path):
    """(N, L, mean diameter) of a packing file (read by the driver, not measured)."""
    from parjam.files import h5md

    pack = h5md.read_packing(path)
    return pack.n, float(pack.L), float(pack.diam.mean())


def arguments(part, L, sigma, args):
    if part == "lstar":
        edges = ",".join(f"{e * sigma / L:.12g}" for e in args.edges_sigma)
        return ["--what", "lstar", "--edges", edges, "--samples", str(args.samples)]
    if part == "cubes":
        return ["--what", "lstar", "--samples", str(args.samples)]
    if part == "structure":
        return ["--what", "structure", "--k", str(args.k),
                "--kmax", f"{4.5 * 2.0 * math.pi / L:.12g}"]
    return ["--what", "speeds"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", nargs="+", required=True, help="P:SMALL.h5:K per point")
    ap.add_argument("--old", required=True, help="parjam executable of main")
    ap.add_argument("--parts", nargs="+", default=list(DEFAULT_PARTS), choices=PARTS)
    ap.add_argument("--max-ranks", nargs="+", default=[],
                    help="PART:P, run PART only up to P ranks (time)")
    ap.add_argument("--edges-sigma", type=float, nargs="+", default=[2.0, 4.0, 8.0, 16.0])
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--work", default=None, help="directory for the tiled packings")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-lengths-weak.md"))
    args = ap.parse_args()
    limit = {p.split(":")[0]: int(p.split(":")[1]) for p in args.max_ranks}
    work = args.work or tempfile.mkdtemp(prefix="parjam-bench-lengths-")
    rows = []
    for spec in args.tiles:
        ranks, small, big = weak_point(spec, work)
        n, L, sigma = box(big)
        for part in args.parts:
            if ranks > limit.get(part, ranks):
                continue
            out = {label: peak_rss(exe, ["lengths", big, "-q"] + arguments(part, L, sigma, args),
                                   ranks) for label, exe in (("old", args.old), ("new", NEW))}
            rows.append((part, ranks, n, out["old"], out["new"]))
            print(f"{part:10s} P={ranks} N={n}: old {out['old'][0]:.0f} MB "
                  f"({out['old'][2]:.1f} s, rc {out['old'][3]}), new {out['new'][0]:.0f} MB "
                  f"({out['new'][2]:.1f} s, rc {out['new'][3]})", flush=True)
    write(args.out, rows, args)


def table_row(part, ranks, n, old, new):
    """One markdown row; a run that failed shows its exit codes (old/new)."""
    flag = "" if new[3] == 0 and old[3] == 0 else f" (exit {old[3]}/{new[3]})"
    return (f"| {part}{flag} | {ranks} | {n} | {n // ranks} | {old[0]:.0f} | {old[1]:.0f} | "
            f"{new[0]:.0f} | {new[1]:.0f} | {new[0] / old[0]:.2f} | {old[2]:.1f} | "
            f"{new[2]:.1f} |")


def write(path, rows, args):
    lines = ["# Peak memory per rank of `parjam lengths`, weak scaling (issue 19)", "",
             "Written by `scripts/bench_lengths_weak.py` (old = main's `parjam`, new = this tree, "
             "in one run; 2D packings tiled from a small jammed one by "
             "`scripts/tile_packing.py`; peak RSS per rank from /usr/bin/time; ranks "
             "oversubscribed on a 2-core machine, which does not change memory).", "",
             f"Parts: `lstar` = cubes of edges {', '.join(f'{e:g}' for e in args.edges_sigma)} "
             f"mean diameters x {args.samples} positions each (the same cubes at every P); "
             f"`structure` = the {args.k} lowest modes (MUMPS shift-and-invert) and F_L, F_T on "
             "the shells |m| <= 4.5; `speeds` = B, G by linear response; `cubes` = the l* "
             f"cubes at the default edges 0.2, 0.3, .., 1 L x {args.samples} positions each.",
             "",
             "| part | P | N | N/P | old max MB | old mean MB | new max MB | new mean MB | "
             "new/old (max) | old s | new s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [table_row(*row) for row in rows]
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
