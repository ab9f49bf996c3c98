#!/usr/bin/env python3
"""Benchmark of the elastic moduli by linear response (``parjam.vib.moduli.compute``: MUMPS-
preconditioned CG, or an iterative preconditioner) against a scipy sparse direct solve of the
same system (SuperLU of D with particle 0 pinned, the d(d+1)/2 strain right-hand sides), in the
same run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_moduli.py \
        --packings bench-out/n4096q/member0000_phi0.6600.h5 \
                   bench-out/n8192q/member0000_phi0.6600.h5 \
        [--ranks 1 2] [--iterative gamg hypre] [--out docs/bench-moduli.md]

Each (packing, ranks, preconditioner) is a separate ``mpirun`` of this script in worker mode;
the worker times the reading, the assembly + solve (``moduli.compute``) and reports the peak
resident memory of every rank (getrusage) and the moduli.  The scipy baseline runs in its own
serial process.  Both must give the same energy tensor (relative difference printed).
"""

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PY = os.path.join(ROOT, ".venv", "bin", "python")


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------- worker (parjam)

def worker(path):
    from parjam import env
    from parjam.files import h5md
    from parjam.vib import moduli

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    t0 = time.perf_counter()
    pack = h5md.read_packing(path)
    t_read = time.perf_counter() - t0
    rss0 = peak_rss_mb()
    comm.tompi4py().Barrier()
    t0 = time.perf_counter()
    error = None
    try:
        mod = moduli.compute(pack, comm)
    except Exception as exc:  # a non-converging iterative solve is a result, not a crash
        mod, error = None, str(exc)
    comm.tompi4py().Barrier()
    t_compute = time.perf_counter() - t0
    rss = comm.tompi4py().gather(peak_rss_mb(), root=0)
    rss0 = comm.tompi4py().gather(rss0, root=0)
    if comm.getRank() == 0:
        out = {"ranks": comm.getSize(), "t_read": t_read, "t_compute": t_compute,
               "rss_before_mb": max(rss0), "rss_peak_mb": max(rss), "error": error}
        if mod is not None:
            s = mod.summary()
            out.update({"B": s["B"], "G": s["G"], "max_residual": s["max_residual"],
                        "iterations": s["iterations"], "pc_type": mod.solver["pc_type"],
                        "N_active": s["N_active"], "Nc": s["Nc"],
                        "c_energy": mod.c_energy.tolist()})
        print("RESULT " + json.dumps(out), flush=True)


# --------------------------------------------------------------------------- baseline (scipy)

def scipy_matrix(an):
    """D of the non-rattlers as a scipy CSR matrix (the same blocks as parjam.vib.hessian)."""
    import numpy as np
    import scipy.sparse as sp

    from parjam.vib import hessian

    brow, bcol, bvals = hessian.half_edge_block_csr(an.n, 0, an.n, an.pi, an.pj, an.blocks)
    return sp.bsr_matrix((bvals, bcol, np.searchsorted(brow, np.arange(an.n + 1))),
                         shape=(an.n * an.d, an.n * an.d)).tocsc()


def baseline(path):
    """u = D^+ Xi by SuperLU with particle 0 pinned (removes the translations; every Xi sums to
    zero, so the pinned solution differs from D^+ Xi by a translation, which Xi . u ignores)."""
    import numpy as np
    import scipy.sparse.linalg as spl

    from parjam import env
    from parjam.files import h5md
    from parjam.vib import moduli

    pack = h5md.read_packing(path)
    rss0 = peak_rss_mb()
    t0 = time.perf_counter()
    an = moduli.active_network(pack, env.petsc().COMM_SELF)  # every half-edge here
    D = scipy_matrix(an)
    rhs = moduli.strain_force_fields(0, an.n, an.pi, an.pj, an.rij, an.blocks)
    t_build = time.perf_counter() - t0
    d = an.d
    t0 = time.perf_counter()
    lu = spl.splu(D[d:, d:].tocsc())
    t_factor = time.perf_counter() - t0
    t0 = time.perf_counter()
    X = np.stack([x.ravel() for x in rhs], axis=1)
    U = np.zeros_like(X)
    U[d:] = lu.solve(np.ascontiguousarray(X[d:]))
    Q = X.T @ U
    t_solve = time.perf_counter() - t0
    res = np.linalg.norm(D @ U - X, axis=0) / np.linalg.norm(X, axis=0)
    c_aff = 0.5 * moduli.affine_tensor(an.rij, an.blocks, pack.volume)  # each contact twice
    c_u = moduli.energy_tensor(c_aff, Q, d, pack.volume)
    s = 0.5 * moduli.tensile_stress(an.rij, an.r, an.sigma, pack.alpha, pack.eps, pack.volume)
    Bt = moduli.stress_strain_tensor(moduli.lagrangian_tensor(c_u, s), s)
    out = {"t_build": t_build, "t_factor": t_factor, "t_solve": t_solve,
           "rss_before_mb": rss0, "rss_peak_mb": peak_rss_mb(),
           "fill": lu.L.nnz + lu.U.nnz, "nnz": D.nnz, "max_residual": float(res.max()),
           "B": moduli.bulk_modulus(Bt), "G": moduli.shear_modulus(Bt),
           "c_energy": c_u.tolist()}
    print("RESULT " + json.dumps(out), flush=True)


# --------------------------------------------------------------------------- driver

def run(cmd, timeout=None):
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"not finished after {timeout:.0f} s (stopped)",
                "wall": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        return {"error": (p.stderr.strip().splitlines() or ["exit %d" % p.returncode])[-1],
                "wall": wall}
    out = json.loads(lines[-1][7:])
    out["wall"] = wall
    return out


def n_particles(path):
    import h5py

    with h5py.File(path, "r") as f:
        return int(f["particles/all/position/value"].shape[-2])


def rel_diff(a, b):
    import numpy as np

    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--packings", nargs="+", required=False)
    ap.add_argument("--ranks", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--iterative", nargs="*", default=["gamg", "hypre"],
                    help="iterative preconditioners tried through -moduli_pc_type")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-moduli.md"))
    ap.add_argument("--json", default=os.path.join(ROOT, "bench-out", "bench-moduli.json"))
    ap.add_argument("--baseline-timeout", type=float, help="stop the scipy baseline after this "
                    "many seconds (it is reported as not finished)")
    ap.add_argument("--no-baseline", type=int, default=10**9, metavar="N",
                    help="skip the scipy baseline for packings with more than N particles")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--baseline", help=argparse.SUPPRESS)
    args, petsc_opts = ap.parse_known_args()
    if args.worker:
        from parjam import env

        env.init(petsc_opts)
        return worker(args.worker)
    if args.baseline:
        return baseline(args.baseline)
    mpirun = shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))
    me = os.path.abspath(__file__)
    rows = []
    for path in args.packings:
        if n_particles(path) > args.no_baseline:
            base = {"error": f"not run (N > {args.no_baseline})"}
        else:
            print(f"{path}: scipy baseline ...", flush=True)
            base = run([PY, me, "--baseline", path], args.baseline_timeout)
        print("   ", {k: v for k, v in base.items() if k != "c_energy"}, flush=True)
        for pc in ["default"] + list(args.iterative):
            opts = [] if pc == "default" else ["-moduli_pc_type", pc, "-moduli_ksp_max_it",
                                               "20000"]
            for ranks in args.ranks:
                print(f"{path}: parjam, {ranks} rank(s), pc {pc} ...", flush=True)
                res = run(mpirun + ["-n", str(ranks), PY, me, "--worker", path] + opts
                          + petsc_opts)
                if "c_energy" in res and "c_energy" in base:
                    res["diff_vs_scipy"] = rel_diff(res["c_energy"], base["c_energy"])
                print("   ", {k: v for k, v in res.items() if k != "c_energy"}, flush=True)
                rows.append({"packing": path, "pc": pc, "ranks": ranks, "parjam": res,
                             "scipy": base})
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(rows, f)
    write_page(rows, args.out)


def write_page(rows, out):
    lines = [
        "| N' | Nc | ranks | preconditioner | parjam compute (s) | iterations | max residual "
        "| peak RSS / rank (MB) | scipy build + factor + solve (s) | scipy peak RSS (MB) "
        "| scipy / parjam time | C^U rel. diff |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, b = r["parjam"], r["scipy"]
        tb = b.get("t_build", 0) + b.get("t_factor", 0) + b.get("t_solve", 0)
        if p.get("error"):
            lines.append(f"| {p.get('N_active', '')} | | {r['ranks']} | {r['pc']} | "
                         f"{p.get('t_compute', float('nan')):.2f} | failed: {p['error']} "
                         "| | | | | | |")
            continue
        its = p["iterations"]
        if b.get("error"):
            scipy_cols = f"{b['error']} | - | > {b['wall'] / p['t_compute']:.0f}" \
                if "wall" in b else f"{b['error']} | - | -"
        else:
            scipy_cols = (f"{tb:.2f} ({b.get('t_factor', 0):.2f} factor) | "
                          f"{b.get('rss_peak_mb', 0):.0f} | {tb / p['t_compute']:.2f}")
        lines.append(
            f"| {p['N_active']} | {p['Nc']} | {r['ranks']} | {p['pc_type']} | "
            f"{p['t_compute']:.2f} | {min(its)}-{max(its)} | {p['max_residual']:.1e} | "
            f"{p['rss_peak_mb']:.0f} (before: {p['rss_before_mb']:.0f}) | {scipy_cols} | "
            f"{p.get('diff_vs_scipy', float('nan')):.1e} |")
    table = "\n".join(lines)
    print(table)
    with open(out + ".table", "w") as f:
        f.write(table + "\n")


if __name__ == "__main__":
    sys.exit(main())
