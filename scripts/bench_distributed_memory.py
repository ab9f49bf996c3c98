#!/usr/bin/env python3
"""Weak scaling of the peak memory per rank of the distributed analysis (issue 19): ``parjam
analyze``, ``parjam dos --method kpm`` and ``parjam moduli`` (CG + GAMG) at a fixed number of
particles per rank, the code of main (OLD, another checkout's ``parjam``) and of this tree (NEW)
side by side in one run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_distributed_memory.py \
        --tiles P:SMALL.h5:K ... --old /work/main/.venv/bin/parjam \
        --out docs/bench-distributed-memory.md

Each ``--tiles P:SMALL:K`` is one point: the packing SMALL tiled K^d times
(scripts/tile_packing.py) run on P ranks.  Every rank runs under /usr/bin/time, which reports
the peak resident set size (max RSS) of that rank; the table gives the largest over the ranks
and the ratio NEW / OLD.  KPM uses few moments and probes and GAMG few iterations: the runs
measure memory, not converged results (a run that fails is marked with its exit code).
Two moduli variants are not run by default (``--commands``): GAMG with the user's global
``-matptap_via allatonce`` on P > 1, and Trilinos ML (``-moduli_pc_type ml``).
"""

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NEW = os.path.join(ROOT, ".venv", "bin", "parjam")
PY = os.path.join(ROOT, ".venv", "bin", "python")

COMMANDS = {
    "analyze": lambda f, out, p: ["analyze", f],
    "dos --method kpm": lambda f, out, p: ["dos", "--method", "kpm", f, "--moments", "64",
                                        "--probes", "2", "--out", out],
    "moduli (GAMG)": lambda f, out, p: ["moduli", f, "-moduli_pc_type", "gamg",
                                     "-moduli_ksp_rtol", "1e-4", "-moduli_ksp_max_it", "400"],
    # GAMG's Galerkin coarse operators A_c = P^T A P with PETSc's memory-lean MPIAIJ PtAP; the
    # option has no per-solver prefix in PETSc 3.18 (GAMG's product matrices carry none), so it
    # is the user's global command-line option, never set by parjam; one rank's (sequential) PtAP
    # has no allatonce and runs as the row above
    "moduli (GAMG, allatonce)": lambda f, out, p: (
        ["moduli", f, "-moduli_pc_type", "gamg", "-moduli_ksp_rtol", "1e-4",
         "-moduli_ksp_max_it", "400"] + (["-matptap_via", "allatonce"] if p > 1 else [])),
    # Trilinos ML (smoothed aggregation too), chosen on the solver's own prefix
    "moduli (ML)": lambda f, out, p: ["moduli", f, "-moduli_pc_type", "ml",
                                      "-moduli_ksp_rtol", "1e-4", "-moduli_ksp_max_it", "400"],
}


def mpirun():
    return shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))


def peak_rss(exe, args, ranks):
    """(max over ranks of the peak RSS in MB, seconds, exit code)."""
    cmd = mpirun() + ["-n", str(ranks), "/usr/bin/time", "-f", "PEAKRSS %M", exe] + args
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ,
                                                                        OMP_NUM_THREADS="1"))
    secs = time.perf_counter() - t0
    kb = [int(m) for m in re.findall(r"PEAKRSS (\d+)", res.stderr)]
    if not kb:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{exe} {' '.join(args)}: no memory report")
    # a failed run (exit code kept in the table) may lose the reports of the ranks mpirun killed
    return max(kb) / 1024.0, secs, res.returncode


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", nargs="+", required=True, help="P:SMALL.h5:K per point")
    ap.add_argument("--old", required=True, help="parjam executable of main")
    ap.add_argument("--commands", nargs="+", default=list(COMMANDS)[:3], choices=list(COMMANDS))
    ap.add_argument("--work", default=None, help="directory for the tiled packings")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-distributed-memory.md"))
    ap.add_argument("--append", action="store_true", help="add the rows to --out's table")
    args = ap.parse_args()
    work = args.work or tempfile.mkdtemp(prefix="parjam-bench-mem-")
    rows = []
    for spec in args.tiles:
        ranks, small, k = spec.split(":")
        ranks, k = int(ranks), int(k)
        tag = os.path.splitext(os.path.relpath(small))[0].replace(os.sep, "_")
        big = os.path.join(work, f"tiled_{tag}_k{k}.h5")
        if not os.path.exists(big):
            made = subprocess.run([PY, os.path.join(ROOT, "scripts", "tile_packing.py"), small,
                                   str(k), big], capture_output=True, text=True, check=True)
            print(made.stdout.strip(), flush=True)
        n = int(re.search(r"N = (\d+)", subprocess.run(
            [NEW, "analyze", "--json", big], capture_output=True, text=True,
            check=True).stdout.replace('"N": ', "N = ")).group(1))
        for name in args.commands:
            out = {}
            for label, exe in (("old", args.old), ("new", NEW)):
                dest = os.path.join(work, f"{label}_{ranks}_{name.split()[0]}.h5")
                if os.path.exists(dest):
                    os.remove(dest)
                out[label] = peak_rss(exe, COMMANDS[name](big, dest, ranks), ranks)
            rows.append((name, ranks, n, out["old"], out["new"]))
            print(f"{name:18s} P={ranks} N={n}: old {out['old'][0]:.0f} MB "
                  f"({out['old'][1]:.1f} s, rc {out['old'][2]}), new {out['new'][0]:.0f} MB "
                  f"({out['new'][1]:.1f} s, rc {out['new'][2]})", flush=True)
    write(args.out, rows, args)


def write(path, rows, args):
    table = [table_row(*row) for row in rows]
    if args.append and os.path.exists(path):
        with open(path) as fh:
            old = fh.read().rstrip("\n").split("\n")
        with open(path, "w") as fh:
            fh.write("\n".join(old + table) + "\n")
        print(f"appended to {path}")
        return
    lines = ["# Peak memory per rank of the distributed analysis (issue 19)", "",
             "Written by `scripts/bench_distributed_memory.py` (old = main's `parjam`, new = this "
             "tree, in one run; 3D packings tiled from small jammed ones by "
             "`scripts/tile_packing.py`; peak RSS per rank from /usr/bin/time, the largest over "
             "the ranks; ranks oversubscribed on a 2-core machine, which does not change memory).",
             "",
             "| command | P | N | N/P | old MB/rank | new MB/rank | new/old | old s | new s |",
             "|---|---|---|---|---|---|---|---|---|"] + table
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {path}")


def table_row(name, ranks, n, old, new):
    """One markdown row; a run that failed shows its exit codes (old/new)."""
    flag = "" if new[2] == 0 and old[2] == 0 else f" (exit {old[2]}/{new[2]})"
    return (f"| {name}{flag} | {ranks} | {n} | {n // ranks} | {old[0]:.0f} | {new[0]:.0f} | "
            f"{new[0] / old[0]:.2f} | {old[1]:.1f} | {new[1]:.1f} |")


if __name__ == "__main__":
    main()
