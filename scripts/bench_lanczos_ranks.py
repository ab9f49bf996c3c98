#!/usr/bin/env python3
"""What the rank-independent Lanczos test costs, old and new in one run (docs/results/stability.md,
"The same bits on any number of ranks").  Run by hand, never in the test suite:

    source scripts/mpi-env
    $PARJAM_MPIRUN -n P .venv/bin/python scripts/bench_lanczos_ranks.py steps FILE.h5 ...
        [--steps 2000] [--repeats 3] [--baseline ba59934] --out bench-out/lanczos-ranks.jsonl
    $PARJAM_MPIRUN -n P .venv/bin/python scripts/bench_lanczos_ranks.py escape FILE.h5 ...
        [--repeats 3] [--baseline ba59934] --out bench-out/lanczos-escape.jsonl

steps: per Lanczos step on the non-rattler Hessian of each packing (e.g. scripts/tile_packing.py
supercells), the baseline's recurrence (PETSc MatMult of the assembled AIJ matrix, numpy sums and
MPI allreduces: parjam/vib/lowest.py at the baseline commit, loaded from git) against the new
one (parjam.vib.rowproduct's product, exact sums), each run for a fixed number of steps (the
failure bound set out of reach), interleaved, repeated; and the product alone, both ways (the
limit: the recurrence's other work is a few vector updates and sums).
escape: a saddle made from each stable packing by moving it along its softest mode until a
contact opens (dense LAPACK: small packings only), checked by the exact inertia; the escape
direction by the baseline's SLEPc Krylov-Schur with shift-and-invert at a target below the
lowest eigenvalue on all ranks (parjam/pack/stability.py at the baseline: ``exact_softest``)
against the new ``softest_direction``: the same on the first rank with the rows gathered in id
order (``root_softest``), and, with -stability_auto_max_dof 0, the Lanczos test run on to
convergence (what larger matrices get): wall seconds, and the eigenvalue of each.
Every record carries the load average at its start (the machine is shared).
"""

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from mpi4py import MPI  # noqa: E402

from parjam import env  # noqa: E402
from parjam.files.h5md import read_packing  # noqa: E402
from parjam.pack import jamnet, stability  # noqa: E402
from parjam.testing import saddles  # noqa: E402
from parjam.vib import lowest  # noqa: E402

COMM = MPI.COMM_WORLD


def baseline_module(commit, path, name):
    """``path`` of the checkout at ``commit`` (git show), imported as module ``name``."""
    text = subprocess.run(["git", "-C", ROOT, "show", f"{commit}:{path}"], check=True,
                          capture_output=True, text=True).stdout
    folder = tempfile.mkdtemp(prefix="parjam-baseline-")
    file = os.path.join(folder, name + ".py")
    with open(file, "w") as f:
        f.write(text)
    spec = importlib.util.spec_from_file_location(name, file)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def timed(fn):
    COMM.Barrier()
    t = time.perf_counter()
    out = fn()
    COMM.Barrier()
    return time.perf_counter() - t, out


def steps_cmd(args):
    PETSc = env.petsc()
    old = baseline_module(args.baseline, "parjam/vib/lowest.py", "baseline_lowest")
    for name in args.files:
        pack = read_packing(name)
        net = jamnet.from_packing(COMM, pack)
        H = stability.active_hessian(net)
        s = stability.shift_for(H.norm)
        start = lowest.start_rows(H.edges.ids, H.d, 1)
        A = H.matrix(PETSc.COMM_WORLD)
        op = H.product(PETSc.COMM_WORLD)
        fixed = lowest.Settings(delta=1e-300, max_steps=args.steps)
        fixed_old = old.Settings(delta=1e-300, max_steps=args.steps)
        x, y = A.createVecs()
        x.array[:] = start.ravel()
        v = start.ravel().copy()
        try:
            for rep in range(args.repeats):
                load = os.getloadavg()[0]
                t_old, r_old = timed(lambda: old.lowest_test(A, H.d, s, start, fixed_old))
                t_new, r_new = timed(lambda: lowest.lowest_test(op, H.d, s, start, fixed))
                k = 200
                p_old, _ = timed(lambda: [A.mult(x, y) for _ in range(k)])
                p_new, _ = timed(lambda: [op.apply(v) for _ in range(k)])
                rec = {"file": os.path.basename(name), "n": pack.n, "d": pack.d,
                       "ranks": COMM.size, "rows": H.n * H.d, "repeat": rep, "load": load,
                       "steps_old": r_old.steps, "steps_new": r_new.steps,
                       "ms_per_step_old": 1e3 * t_old / r_old.steps,
                       "ms_per_step_new": 1e3 * t_new / r_new.steps,
                       "ms_per_product_old": 1e3 * p_old / k,
                       "ms_per_product_new": 1e3 * p_new / k,
                       "lowest_old": r_old.lowest, "lowest_new": r_new.lowest}
                emit(args.out, rec)
        finally:
            for obj in (A, op, x, y):
                obj.destroy()


def escape_cmd(args):
    PETSc = env.petsc()
    old = baseline_module(args.baseline, "parjam/pack/stability.py", "baseline_stability")
    world = PETSc.COMM_WORLD
    for name in args.files:
        pack = saddles.along_soft_mode(read_packing(name)) if COMM.rank == 0 else None
        pack = COMM.bcast(pack, root=0)
        net = jamnet.from_packing(COMM, pack)
        cur = stability.check(world, net, stability.Settings("inertia"))
        for rep in range(args.repeats):
            load = os.getloadavg()[0]
            t_old, (_, lam_old) = timed(lambda: old.exact_softest(world, net, cur))
            t_new, (_, lam_new) = timed(lambda: stability.softest_direction(world, net, cur))
            opts = PETSc.Options()
            opts["stability_auto_max_dof"] = 0  # the Lanczos vector, as above that size
            try:
                t_lz, (_, lam_lz) = timed(lambda: stability.softest_direction(world, net, cur))
            finally:
                opts.delValue("stability_auto_max_dof")
            emit(args.out, {"file": os.path.basename(name), "n": pack.n, "d": pack.d,
                            "ranks": COMM.size, "n_negative": cur.n_negative, "repeat": rep,
                            "load": load, "s_old": t_old, "s_root": t_new, "s_lanczos": t_lz,
                            "lambda_old": lam_old, "lambda_root": lam_new,
                            "lambda_lanczos": lam_lz})


def emit(out, rec):
    if COMM.rank != 0:
        return
    print(json.dumps(rec), flush=True)
    if out:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, "a") as f:
            f.write(json.dumps(rec) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for cmd in ("steps", "escape"):
        p = sub.add_parser(cmd)
        p.add_argument("files", nargs="+")
        p.add_argument("--repeats", type=int, default=3)
        p.add_argument("--baseline", default="ba59934")
        p.add_argument("--out", default=None)
        if cmd == "steps":
            p.add_argument("--steps", type=int, default=2000)
    args = ap.parse_args()
    env.petsc()
    (steps_cmd if args.cmd == "steps" else escape_cmd)(args)


if __name__ == "__main__":
    main()
