#!/usr/bin/env python3
"""Benchmark of parjam's spectra against scipy and dense numpy, on the same Hessians, in one run.

    source scripts/mpi-env
    .venv/bin/python scripts/bench_spectrum.py --packings A.h5 B.h5 ... --k 100 \
        --slice C.h5 --out docs/bench-spectra.md

For each packing (3D, full matrix of the non-rattlers, translations removed):
- parjam ``sinvert`` (SLEPc Krylov-Schur + MUMPS LDL^T, translations deflated) on 1 and 2 ranks,
  with the PETSc log events of the solve: factorisation, MatSolve count and time, EPSSolve; the
  "limit" is one factorisation (symbolic + numeric) plus 2k solves at the measured cost per solve;
- scipy.sparse.linalg.eigsh(sigma = target, which = "LM") for k + d eigenvalues (it cannot
  deflate; the d translations are dropped afterwards), and optionally scipy's SuperLU factor alone
  (its fill);
- dense numpy eigvalsh (all eigenvalues) for N <= --dense-max.
For the --slice packing: every mode below the frequency holding --slice-fraction of the spectrum
by parjam ``slice`` on 1 and 2 ranks (2 partitions) against the dense count.

Every method runs in its own process (time and peak memory ru_maxrss of each process); residuals
||H v - lambda v|| / ||H||_inf are computed the same way for all.  Workers print one JSON line.
"""

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
PY = sys.executable
TAG = "BENCH_JSON "


def peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def emit(record):
    print(TAG + json.dumps(record, default=float), flush=True)


# --- workers ---------------------------------------------------------------------------------------
def load_system(path):
    from parjam.files import h5md
    from parjam.vib import spectrum

    t0 = time.perf_counter()
    system = spectrum.active_system(h5md.read_packing(path))
    return system, time.perf_counter() - t0


def worker_parjam(args, petsc_args):
    from parjam import env

    env.init(petsc_args)
    PETSc = env.petsc()
    PETSc.Log.begin()
    from parjam.vib import spectrum

    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    system, t_load = load_system(args.file)
    mpi.Barrier()
    t0 = time.perf_counter()
    if args.window:
        spec = spectrum.compute(comm, system, "full", window=tuple(args.window), method="slice",
                                tol=args.tol)
    else:
        spec = spectrum.compute(comm, system, "full", k=args.k, method="sinvert", tol=args.tol)
    mpi.Barrier()
    wall = time.perf_counter() - t0
    stage = PETSc.Log.Stage("modes: eigensolve").id
    events = {}
    for name in ("MatCholFctrSym", "MatCholFctrNum", "MatSolve", "EPSSolve", "MatGetInertia"):
        info = PETSc.Log.Event(name).getPerfInfo(stage)
        events[name] = {"count": int(info["count"]), "time": mpi.allreduce(info["time"],
                                                                           op=_max())}
    mem = mpi.gather(peak_mb())
    if comm.getRank() == 0:
        emit({"method": "parjam-" + ("slice" if args.window else "sinvert"),
              "ranks": comm.getSize(), "dof": system.dof, "n_active": system.n,
              "k": len(spec.eigenvalue), "n_requested": spec.n_requested, "wall": wall,
              "load": t_load, "events": events, "info": spec.info,
              "max_error": float(spec.error.max()) if len(spec.error) else 0.0,
              "complete": spec.complete, "eigenvalues": spec.eigenvalue.tolist(),
              "peak_mb_max": max(mem), "peak_mb_sum": sum(mem)})


def _max():
    from mpi4py import MPI

    return MPI.MAX


def scipy_hessian(system):
    """The same matrix as parjam's, assembled by scipy (CSR) from the same contact blocks."""
    import scipy.sparse as sp

    blocks = system.blocks("full")
    d = system.d
    i, j = system.i, system.j
    rows, cols, vals = [], [], []
    a = np.arange(d)
    for (p, q, sign) in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((p[:, None, None] * d + a[None, :, None]).repeat(d, axis=2).ravel())
        cols.append((q[:, None, None] * d + a[None, None, :]).repeat(d, axis=1).ravel())
        vals.append((sign * blocks).ravel())
    n = system.dof
    H = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n, n)).tocsr()
    H.sum_duplicates()
    return H


def cap_memory(gb):
    """Address-space cap for a baseline worker: a MemoryError instead of the machine's OOM killer
    (the machine is shared)."""
    if gb:
        lim = int(gb * 1024**3)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))


def worker_scipy(args):
    cap_memory(args.mem_limit_gb)
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla

    from parjam.vib import spectrum

    system, t_load = load_system(args.file)
    H = scipy_hessian(system)
    norm = float(abs(H).sum(axis=1).max())
    sigma = -spectrum.ZERO_TOL * norm
    t0 = time.perf_counter()
    lam, V = sla.eigsh(H, k=args.k + system.d, sigma=sigma, which="LM")
    wall = time.perf_counter() - t0
    order = np.argsort(lam)
    lam, V = lam[order], V[:, order]
    translations = lam[:system.d]
    lam, V = lam[system.d:], V[:, system.d:]
    err = np.linalg.norm(H @ V - V * lam, axis=0) / norm
    rec = {"method": "scipy-eigsh", "ranks": 1, "dof": system.dof, "k": len(lam), "wall": wall,
           "max_error": float(err.max()), "eigenvalues": lam.tolist(),
           "max_translation": float(np.abs(translations).max()), "peak_mb_max": peak_mb()}
    if args.fill:
        t0 = time.perf_counter()
        lu = sla.splu(sp.csc_matrix(H - sigma * sp.identity(H.shape[0])))
        rec["superlu_seconds"] = time.perf_counter() - t0
        rec["superlu_fill"] = int(lu.L.nnz + lu.U.nnz)
        rec["peak_mb_max"] = peak_mb()
    emit(rec)


def worker_dense(args):
    cap_memory(args.mem_limit_gb)
    from parjam.vib import spectrum

    system, t_load = load_system(args.file)
    H = spectrum.dense_matrix(system, "full")
    t0 = time.perf_counter()
    lam = np.linalg.eigvalsh(H)
    wall = time.perf_counter() - t0
    emit({"method": "numpy-eigvalsh", "ranks": 1, "dof": system.dof, "wall": wall,
          "n_modes": system.n_modes, "eigenvalues": lam[system.d:].tolist(),
          "max_translation": float(np.abs(lam[:system.d]).max()), "peak_mb_max": peak_mb()})


# --- driver ----------------------------------------------------------------------------------------
def run_worker(kind, file, ranks=1, extra=(), petsc=(), timeout=3600):
    mpirun = shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))
    cmd = [PY, os.path.abspath(__file__), "--worker", kind, "--file", file, *extra, *petsc]
    if kind == "parjam":
        cmd = mpirun + ["-n", str(ranks)] + cmd
    print("#", " ".join(cmd), file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)
    except subprocess.TimeoutExpired:
        return {"method": kind, "ranks": ranks, "failed": f"timeout after {timeout} s"}
    for line in res.stdout.splitlines():
        if line.startswith(TAG):
            rec = json.loads(line[len(TAG):])
            rec["process_seconds"] = time.perf_counter() - t0
            return rec
    return {"method": kind, "ranks": ranks,
            "failed": (res.stderr.strip().splitlines() or ["no output"])[-1][:200]}


def compare(a, b):
    """Largest relative difference of two eigenvalue lists (same length)."""
    x, y = np.asarray(a["eigenvalues"]), np.asarray(b["eigenvalues"])
    m = min(len(x), len(y))
    return float(np.max(np.abs(x[:m] / y[:m] - 1))) if m else float("nan")


def bench_lowest(path, args):
    k = ["--k", str(args.k), "--tol", str(args.tol)]
    out = {"file": path, "runs": []}
    for r in args.ranks:
        out["runs"].append(run_worker("parjam", path, r, k, args.petsc, args.timeout))
    system_dof = out["runs"][0].get("dof", 0)
    cap = ["--mem-limit-gb", str(args.mem_limit_gb)]
    if system_dof // 3 <= args.scipy_max:
        fill = ["--fill"] if system_dof // 3 <= args.fill_max else []
        out["runs"].append(run_worker("scipy", path, 1, ["--k", str(args.k)] + fill + cap,
                                      timeout=args.timeout))
    if system_dof // 3 <= args.dense_max:
        out["runs"].append(run_worker("dense", path, 1, cap, timeout=args.timeout))
    return out


def bench_slice(path, args, lowest=()):
    """Slicing against the dense spectrum (reused from the lowest-mode runs of the same file)."""
    dense = next((r for case in lowest if case["file"] == path for r in case["runs"]
                  if r.get("method") == "numpy-eigvalsh" and "failed" not in r), None)
    dense = dense or run_worker("dense", path, 1, ["--mem-limit-gb", str(args.mem_limit_gb)],
                                timeout=args.timeout)
    out = {"file": path, "dense": dense, "runs": []}
    if "failed" in dense:
        return out
    lam = np.asarray(dense["eigenvalues"])
    m = int(args.slice_fraction * len(lam))
    wb = float(np.sqrt(0.5 * (lam[m - 1] + lam[m])))
    out["window"], out["dense_count"] = (0.0, wb), m
    for r in args.ranks:
        petsc = list(args.petsc) + (["-modes_eps_krylovschur_partitions", str(r)] if r > 1
                                    else [])
        rec = run_worker("parjam", path, r, ["--window", "0", str(wb), "--tol", str(args.tol)],
                         petsc, args.timeout)
        out["runs"].append(rec)
    return out


def fmt(x, spec=".3g"):
    return "-" if x is None else format(x, spec)


def markdown(lowest, slices, args):
    lines = ["# Benchmark: lowest modes and spectrum slicing (parjam vs scipy vs numpy)", "",
             f"Generated by `scripts/bench_spectrum.py` on {time.strftime('%Y-%m-%d %H:%M')}"
             f" ({os.cpu_count()} cores, shared; OMP/BLAS threads = "
             f"{os.environ.get('OMP_NUM_THREADS', '?')}). All numbers of one table come from "
             "one run; compare ratios, not absolute times (the machine is shared).", "",
             f"Lowest k = {args.k} non-translational modes of the full matrix (3D, non-rattlers, "
             f"translations removed), parjam tolerance {args.tol:g} on "
             "||Hv - lambda v|| / ||H||_inf; 'limit' = one factorisation (symbolic + numeric) + "
             "2k MatSolve at the measured cost per solve; 'solve/limit' = EPSSolve / limit.", ""]
    head = ("| N' | dof | method | ranks | time (s) | speed-up vs scipy | max residual | "
            "max rel. diff vs scipy | vs dense | peak MB (max rank / sum) | factor fill | ordering | "
            "MatSolve calls | solve/limit |")
    lines += [head, "|" + "---|" * (head.count("|") - 1)]
    for case in lowest:
        runs = case["runs"]
        scipy_run = next((r for r in runs if r.get("method") == "scipy-eigsh"
                          and "failed" not in r), None)
        dense_run = next((r for r in runs if r.get("method") == "numpy-eigvalsh"
                          and "failed" not in r), None)
        for r in runs:
            lines.append(row(r, scipy_run, dense_run, args.k))
        if scipy_run and "superlu_fill" in scipy_run:
            lines.append(f"|  | {scipy_run['dof']} | scipy SuperLU factor alone | 1 | "
                         f"{scipy_run['superlu_seconds']:.3g} |  |  |  |  |  | "
                         f"{scipy_run['superlu_fill'] / 1e6:.1f} M |  |  |  |")
    lines += ["", "## Spectrum slicing against dense", ""]
    for case in slices:
        d = case["dense"]
        if "failed" in d:
            lines.append(f"dense reference failed: {d['failed']}")
            continue
        lines.append(f"Packing `{os.path.basename(case['file'])}`: {d['dof']} dof; window "
                     f"omega in [0, {case['window'][1]:.4g}] holding {case['dense_count']} modes "
                     f"({100 * case['dense_count'] / d['n_modes']:.1f} % of the spectrum); dense "
                     f"numpy eigvalsh (all eigenvalues) {d['wall']:.3g} s, peak "
                     f"{d['peak_mb_max']:.0f} MB.")
        lines += ["", "| method | ranks | time (s) | speed-up vs dense | modes found | count "
                  "(inertia) | dense count | max rel. diff vs dense | max residual | peak MB |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in case["runs"]:
            if "failed" in r:
                lines.append(f"| parjam slice | {r['ranks']} | failed: {r['failed']} |"
                             + " |" * 7)
                continue
            dens = {"eigenvalues": d["eigenvalues"][:len(r["eigenvalues"])]}
            lines.append(f"| parjam slice | {r['ranks']} | {r['wall']:.3g} | "
                         f"{d['wall'] / r['wall']:.2f} | {r['k']} | {r['n_requested']} | "
                         f"{case['dense_count']} | {compare(r, dens):.1e} | "
                         f"{r['max_error']:.1e} | {r['peak_mb_max']:.0f} |")
    return "\n".join(lines) + "\n"


def row(r, scipy_run, dense_run, k):
    if "failed" in r:
        return f"| | | {r['method']} | {r['ranks']} | failed: {r['failed']} |" + " |" * 10
    speed = scipy_run["wall"] / r["wall"] if scipy_run else None
    diff = compare(r, scipy_run) if scipy_run and r is not scipy_run else None
    ddiff = None
    if dense_run and r is not dense_run:
        ddiff = compare(r, {"eigenvalues": dense_run["eigenvalues"][:len(r["eigenvalues"])]})
    fill = ordering = calls = ratio = None
    if r["method"].startswith("parjam"):
        info, ev = r["info"], r["events"]
        fill = info.get("factor_entries", 0) / 1e6
        ordering = f"{info.get('ordering', '?')} ({info.get('analysis', '?')})"
        calls = ev["MatSolve"]["count"]
        per_solve = ev["MatSolve"]["time"] / max(calls, 1)
        limit = ev["MatCholFctrSym"]["time"] + ev["MatCholFctrNum"]["time"] + 2 * k * per_solve
        ratio = ev["EPSSolve"]["time"] / limit if limit > 0 else None
    mem = f"{r['peak_mb_max']:.0f}" + (f" / {r['peak_mb_sum']:.0f}" if "peak_mb_sum" in r else "")
    return (f"| {r.get('n_active', r['dof'] // 3)} | {r['dof']} | {r['method']} | {r['ranks']} | "
            f"{r['wall']:.3g} | {fmt(speed, '.2f')} | {fmt(r.get('max_error'), '.1e')} | "
            f"{fmt(diff, '.1e')} | {fmt(ddiff, '.1e')} | {mem} | {fmt(fill, '.1f')}{' M' if fill else ''} | "
            f"{ordering or '-'} | {fmt(calls, 'd')} | {fmt(ratio, '.2f')} |")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worker", choices=("parjam", "scipy", "dense"))
    p.add_argument("--file")
    p.add_argument("--k", type=int, default=100)
    p.add_argument("--window", type=float, nargs=2)
    p.add_argument("--fill", action="store_true")
    p.add_argument("--tol", type=float, default=1e-10)
    p.add_argument("--packings", nargs="*", default=[])
    p.add_argument("--slice", nargs="*", default=[])
    p.add_argument("--slice-fraction", type=float, default=0.1)
    p.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    p.add_argument("--scipy-max", type=int, default=40000, help="largest N for scipy")
    p.add_argument("--fill-max", type=int, default=10000, help="largest N for SuperLU alone")
    p.add_argument("--dense-max", type=int, default=4096)
    p.add_argument("--timeout", type=float, default=3600)
    p.add_argument("--mem-limit-gb", type=float, default=10.0,
                   help="address-space cap of the scipy and dense workers")
    p.add_argument("--out", default="docs/bench-spectra.md")
    p.add_argument("--json", default="bench-out/bench-spectra.json")
    args, petsc = p.parse_known_args()
    args.petsc = petsc
    if args.worker == "parjam":
        return worker_parjam(args, petsc)
    if args.worker == "scipy":
        return worker_scipy(args)
    if args.worker == "dense":
        return worker_dense(args)
    lowest = [bench_lowest(f, args) for f in args.packings]
    slices = [bench_slice(f, args, lowest) for f in args.slice]
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump({"lowest": lowest, "slices": slices}, fh, default=float)
    with open(args.out, "w") as fh:
        fh.write(markdown(lowest, slices, args))
    print(f"wrote {args.out} and {args.json}")


if __name__ == "__main__":
    main()
