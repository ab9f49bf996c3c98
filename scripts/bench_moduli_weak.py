#!/usr/bin/env python3
"""Weak scaling of ``parjam moduli``'s peak memory per rank by preconditioner (issue 19): the CG
solves of the linear response with several preconditioners side by side in one run, at a fixed
number of particles per rank.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_moduli_weak.py \
        --tiles 1:SMALL128.h5:6 2:SMALL256.h5:6 4:SMALL512.h5:6 \
        --out docs/bench-moduli-weak.md

The run in docs/bench-moduli-weak.md used packings made by ``parjam pack --dim 3 --n N --dphi
1e-1 3e-2 --seed 7 --members 2 --phic-method extrapolate`` (N = 128, 256, 512, 1024), the
dphi = 1e-1 state of member 1, 1, 0, 0 (with a positive softest shear modulus), K = 6; the MUMPS
row at P = 2 and the P = 8 rows were added with ``--configs ... --append``.

Each ``--tiles P:SMALL:K`` is one point: the packing SMALL tiled K^d times
(scripts/tile_packing.py) run on P ranks.  A tiled packing has exactly the moduli of its small
one, so every point is checked against SMALL's moduli by the default solver (MUMPS Cholesky on
one rank): the table gives B, G and their relative difference to that reference.  SMALL must be
stable in its fixed box with its copies (a packing with a negative softest shear modulus gives a
tiled D with negative eigenvalues, on which CG stops with DIVERGED_INDEFINITE_MAT).  Every rank
runs under /usr/bin/time (peak RSS per rank; the table gives the largest over the ranks; ranks
oversubscribed on a shared 2-core machine: seconds are indicative only).
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXE = os.path.join(ROOT, ".venv", "bin", "parjam")
PY = os.path.join(ROOT, ".venv", "bin", "python")
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from peak_rss import measured  # noqa: E402
from tile_packing import weak_point  # noqa: E402

# name -> options of ``parjam moduli`` given P (the PC on the solver's own prefix ``moduli_``)
CONFIGS = {
    # parjam's default: MUMPS Cholesky on one rank, block Jacobi (PCASM, no overlap) + ICC(0)
    # on several (parjam.vib.moduli.response_solver)
    "default": lambda p: [],
    "bjacobi + ICC(0)": lambda p: ["-moduli_pc_type", "bjacobi", "-moduli_sub_pc_type", "icc"],
    "GAMG": lambda p: ["-moduli_pc_type", "gamg"],
    "GAMG, agg_nsmooths 0": lambda p: ["-moduli_pc_type", "gamg",
                                       "-moduli_pc_gamg_agg_nsmooths", "0"],
    # the user's global option (parjam never sets it); one rank's PtAP has no allatonce
    "GAMG, global -matptap_via allatonce": lambda p: (
        ["-moduli_pc_type", "gamg"] + (["-matptap_via", "allatonce"] if p > 1 else [])),
    "ASM(1) + ICC(0)": lambda p: ["-moduli_pc_type", "asm", "-moduli_pc_asm_overlap", "1",
                                 "-moduli_sub_pc_type", "icc"],
    # the default on P > 1 until issue 19 (MUMPS available): a distributed factorisation
    "MUMPS Cholesky": lambda p: ["-moduli_pc_type", "cholesky",
                                 "-moduli_pc_factor_mat_solver_type", "mumps"],
    "hypre BoomerAMG": lambda p: ["-moduli_pc_type", "hypre", "-moduli_pc_hypre_type",
                                  "boomeramg", "-moduli_pc_hypre_boomeramg_nodal_coarsen", "6",
                                  "-moduli_pc_hypre_boomeramg_vec_interp_variant", "3"],
}


def run(args, ranks):
    """(peak RSS MB (max over ranks), seconds, exit code, B, G, iterations) of one run."""
    mb, secs, res = measured(ranks, [EXE, "moduli"] + args, f"moduli {' '.join(args)}")
    B = re.search(r"bulk modulus B\s+(\S+)", res.stdout)
    G = re.search(r"shear modulus G\s+(\S+)", res.stdout)
    it = re.search(r"iterations ([\d ]+),", res.stdout)
    return (max(mb), secs, res.returncode, float(B.group(1)) if B else None,
            float(G.group(1)) if G else None, max(map(int, it.group(1).split())) if it else None)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", nargs="+", required=True, help="P:SMALL.h5:K per point")
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS)[:5], choices=list(CONFIGS))
    ap.add_argument("--work", default=None, help="directory for the tiled packings")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-moduli-weak.md"))
    ap.add_argument("--append", action="store_true", help="add the rows to --out's table")
    args = ap.parse_args()
    head = None
    if args.append and os.path.exists(args.out):
        with open(args.out) as fh:
            head = fh.read().rstrip("\n").split("\n")
    work = args.work or tempfile.mkdtemp(prefix="parjam-bench-moduli-")
    rows = []
    for spec in args.tiles:
        ranks, small, big = weak_point(spec, work)
        ref = run([small, "-q"], 1)  # the small packing's moduli, default solver, one rank
        n = int(re.search(r"N = (\d+)", subprocess.run(
            [EXE, "analyze", "--json", big], capture_output=True, text=True,
            check=True).stdout.replace('"N": ', "N = ")).group(1))
        for name in args.configs:
            res = run([big, "-q"] + CONFIGS[name](ranks), ranks)
            rows.append((name, ranks, n, res, ref))
            print(table_row(*rows[-1]), flush=True)
            write(args.out, rows, head)


def rel(x, ref):
    return "-" if x is None or ref is None else f"{abs(x - ref) / abs(ref):.1e}"


def table_row(name, ranks, n, res, ref):
    mb, secs, rc, B, G, its = res
    flag = "" if rc == 0 else f" (exit {rc})"
    fmt = (lambda v: "-" if v is None else f"{v:.6e}")
    return (f"| {name}{flag} | {ranks} | {n} | {n // ranks} | {mb:.0f} | "
            f"{'-' if its is None else its} | {secs:.1f} | {fmt(B)} | {fmt(G)} | "
            f"{rel(B, ref[3])} | {rel(G, ref[4])} |")


HEADER = [
    "# Moduli: peak memory per rank by preconditioner, weak scaling (issue 19)", "",
    "Written by `scripts/bench_moduli_weak.py`: `parjam moduli` (CG to the default "
    "relative tolerance 1e-11) on 3D packings tiled 6^3 times from small stable jammed "
    "ones (`scripts/tile_packing.py`), one small packing per P (N = 128, 256, 512); "
    "peak RSS per rank from /usr/bin/time (largest over the ranks); iterations = the "
    "largest of the d(d+1)/2 solves; dB, dG = relative difference to the small "
    "packing's moduli by the default solver (MUMPS Cholesky, one rank), which a tiled "
    "packing shares exactly (to the 7 digits parjam prints: 0 means below 5e-7). Ranks "
    "oversubscribed on a shared 2-core machine: seconds "
    "are indicative only. default = parjam's default: MUMPS Cholesky on one rank, "
    "block Jacobi (PCASM without overlap) with ICC(0) blocks on several.", "",
    "| preconditioner | P | N | N/P | MB/rank | iterations | s | B | G | dB | dG |",
    "|---|---|---|---|---|---|---|---|---|---|---|"]


def write(path, rows, head=None):
    """The page: a new table, or ``head`` (the page's lines) with the rows added."""
    lines = head[:] if head else HEADER[:]
    lines += [table_row(*row) for row in rows]
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
