#!/usr/bin/env python3
"""Benchmark of ``parjam softmodes`` (3D, near-isostatic packings, one cut at x = L/2) against the
dense baseline (LAPACK SVD of the rigidity matrix, what the reference implementation does), in
the same run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_softmodes.py [--sizes 1024 4096 16384] [--ranks 1 2]
        [--dense-max 4096] [--krylov-timeout 600] [--conditions "quiet"]
        [--out docs/bench-softmodes.md]

Missing packings are made with ``parjam pack --dim 3 --n N --dphi 1e-8 --phic-method
extrapolate --seed 1`` under bench-out/ (the bisection takes hours at N = 16384 here).  Each (N, ranks) run is a separate ``mpirun`` of the command line;
its stage times and peak memory per rank come from the output file.  Both null-basis methods
run: block inverse iteration (the default) on every rank count, SLEPc Krylov-Schur on 1 rank
(stopped after --krylov-timeout seconds).  The dense baseline runs in its own process (one
thread, like one rank) and also checks that both bases span the same space.
"""

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PY = os.path.join(ROOT, ".venv", "bin", "python")
PARJAM = os.path.join(ROOT, ".venv", "bin", "parjam")


def packing_path(workdir, n):
    return os.path.join(workdir, f"soft{n}", "member0000_dphi1.0e-08.h5")


def ensure_packing(workdir, n, phic_method="extrapolate"):
    path = packing_path(workdir, n)
    if not os.path.exists(path):
        print(f"making the N = {n} packing (slow for large N) ...", flush=True)
        t0 = time.time()
        subprocess.run([PARJAM, "pack", "--dim", "3", "--n", str(n), "--dphi", "1e-8",
                        "--phic-method", phic_method, "--members", "1", "--seed", "1",
                        "--out", os.path.dirname(path)], check=True)
        print(f"N = {n} packing: {time.time() - t0:.0f} s", flush=True)
    return path


def run_parjam(path, n, ranks, workdir, vectors, basis="block", timeout=None):
    """One ``mpirun parjam softmodes``; None if it was stopped after ``timeout`` seconds."""
    out = os.path.join(workdir, f"soft{n}_r{ranks}_{basis}.h5")
    mpirun = shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))
    cmd = mpirun + ["-n", str(ranks), PARJAM, "softmodes", path, "--cut", "x=0.5", "--out", out,
                    "-q", "--allow-hyperstatic", "--basis", basis] + (["--vectors"] if vectors else [])
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, start_new_session=True)
    try:
        rc = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)  # mpirun and its ranks
        proc.wait()
        return None
    if rc != 0:
        raise subprocess.CalledProcessError(rc, cmd)
    wall = time.perf_counter() - t0
    return dict(read_result(out), wall=wall, ranks=ranks, file=out, basis=basis)


def read_result(out):
    import h5py
    import numpy as np

    with h5py.File(out, "r") as f:
        g = f["softmodes"]
        cnt = g["count"].attrs
        te = g["trial_energy"].attrs
        ext = g["extension"][()]
        E = g["trial_energy"][()]
        sel = ext > te["e0"]
        return {
            "count": int(g["count"][()]), "q": int(cnt["q"]), "N_active": int(cnt["N_active"]),
            "expected": int(cnt["expected_if_isostatic"]), "excess": int(cnt["excess"]),
            "localised": int(cnt["localised"]), "eq3": float(cnt["eq3_residual"]),
            "ortho": float(cnt["orthonormality"]), "gap": float(cnt["gap"]),
            "t_count": float(g.attrs["seconds_count"]),
            "t_null": float(g.attrs["seconds_null_space"]),
            "t_analysis": float(g.attrs["seconds_analysis"]),
            "rss": float(g.attrs["peak_rss_mb"]), "iterations": int(g.attrs["iterations"]),
            "c": float(g["overlap"].attrs["c"]), "c_nt": float(g["overlap"].attrs["c_nontrivial"]),
            "f": g["overlap"][()].tolist(), "fractions": g["extended_fraction"][()].tolist(),
            "omega_t2": float(te["omega_t2"]), "omega_L2": float(te["omega_L2"]),
            "E_max": float(np.max(E[sel])) if sel.any() else float("nan"),
            "q_prime": int(te["q_prime"]), "n_below": int(te["n_below_2omega_t2"]),
        }


DENSE = r"""
import json, resource, sys, time
import numpy as np
from parjam import env, softmodes as sm; from parjam.files import h5md
from parjam.testing import softmodes_reference as ref
env.init()
path, basis_file = sys.argv[1], sys.argv[2]
pack = h5md.read_packing(path)
cs = sm.prepare(pack, [sm.Plane(0, 0.5)], allow_hyperstatic=True).gathered()  # one rank
t0 = time.perf_counter()
S = ref.dense_rigidity(cs, cs.kept)
if basis_file != "-":  # count and basis: the same job as parjam
    dim, N0, s = ref.dense_null_space(S)
else:  # count only (singular values): a lower bound on the baseline's cost
    s = np.linalg.svd(S, compute_uv=False)
    dim = S.shape[1] - int(np.count_nonzero(s > 1e-8 * s[0]))
seconds = time.perf_counter() - t0
out = {"seconds": seconds, "count": int(dim), "vectors": basis_file != "-",
       "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}
if basis_file != "-":
    import h5py
    with h5py.File(basis_file, "r") as f:
        B = f["softmodes/basis"][()]
    V = B[:, cs.original, :].reshape(B.shape[0], -1).T
    T = np.kron(np.ones((cs.n, 1)), np.eye(cs.d)) / np.sqrt(cs.n)
    cos = np.linalg.svd(N0.T @ np.hstack([V, T]), compute_uv=False)
    out["min_cosine"] = float(cos.min())
print("DENSE " + json.dumps(out))
"""


def run_dense(path, basis_file):
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.run([PY, "-c", DENSE, path, basis_file or "-"], check=True, env=env,
                          capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("DENSE ")][-1]
    return dict(json.loads(line[6:]), wall=wall)


def dense_cells(r, dn):
    """The baseline's four columns, on the 1-rank row of each size."""
    if r["ranks"] != 1:
        return " | | | "
    if dn is None:
        gb = 8 * (3 * r["N_active"]) ** 2 / 2**30
        return f"not run (S alone: {gb:.0f} GB dense) | | | "
    ratio = dn["seconds"] / (r["t_count"] + r["t_null"])
    what = "" if dn["vectors"] else " (count only)"
    cos = f"{dn['min_cosine']:.12f}" if "min_cosine" in dn else "-"
    return f"{dn['seconds']:.1f}{what} | {dn['peak_mb']:.0f} | {ratio:.1f}x | {cos}"


def method_table(rows, krylov, timeout):
    """Block inverse iteration against SLEPc Krylov-Schur, 1 rank, same packing."""
    lines = ["", "## Null basis: block inverse iteration against SLEPc Krylov-Schur (1 rank)", "",
             "Same packing, same count; the basis step only (`basis s`). Krylov-Schur: "
             "shift-and-invert at -1e-8 k, mpd 256, restart 0.8, translations deflated.", "",
             "| N | modes | block s | block passes | Krylov-Schur s | Krylov / block | gap (block) "
             "k | gap (Krylov) k |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["ranks"] != 1 or r["n"] not in krylov:
            continue
        kr = krylov[r["n"]]
        if kr is None:
            lines.append(f"| {r['n']} | {r['count'] - 3} | {r['t_null']:.1f} | {r['iterations']} "
                         f"| stopped after {timeout:.0f} s (wall) | > {timeout / r['t_null']:.0f}x "
                         f"| {r['gap']:.4e} | - |")
        else:
            lines.append(f"| {r['n']} | {r['count'] - 3} | {r['t_null']:.1f} | {r['iterations']} "
                         f"| {kr['t_null']:.1f} | {kr['t_null'] / r['t_null']:.1f}x "
                         f"| {r['gap']:.4e} | {kr['gap']:.4e} |")
    return lines


def markdown(rows, dense, host, conditions, krylov, timeout):
    lines = [
        "# Benchmark: `parjam softmodes` (3D, one cut at x = L/2)",
        "",
        "Made by `scripts/bench_softmodes.py` (run by hand; see its docstring). Near-isostatic "
        "packings (`parjam pack --dim 3 --n N --dphi 1e-8 --phic-method extrapolate --seed 1`), "
        "rattlers removed, one plane cut at "
        "x = L/2. parjam: MUMPS inertia count at two thresholds, null basis by block inverse "
        "iteration (one MUMPS factor of M + 1e-8 k I, column blocks of 64 right-hand sides "
        "(`--columns`, the default; the last block carries 8 extra), Rayleigh-Ritz per block; "
        "the default) with the translations deflated, Eq. 3 residuals, "
        "extension, f(x) and trial modes. Baseline: dense LAPACK SVD of the rigidity matrix S (numpy, "
        "one thread), the reference implementation's method, run in the same session: count "
        "and null basis (with the smallest cosine between the two bases' spans, 1 = same "
        "space) or, for the larger sizes, the singular values only (count only, a lower bound "
        "on its cost). The ratio compares the baseline's seconds with parjam's count + basis "
        "seconds on 1 rank. `peak MB` is the largest resident set of any one rank (parjam) or "
        "of the baseline process.",
        "",
        f"Machine: {host}. Conditions: {conditions}",
        "",
        "| N | N' | Nc - Nc_iso | q | null space (d+q-1) | ranks | wall s | count s | basis s | analysis s "
        "| passes | peak MB/rank | Eq. 3 residual | dense SVD s | dense peak MB "
        "| dense / parjam (1 rank, count + basis) | subspace min cos |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['N_active']} | {r['excess']:+d} | {r['q']} | "
            f"{r['count']} ({r['expected']}) | "
            f"{r['ranks']} | {r['wall']:.1f} | {r['t_count']:.2f} | {r['t_null']:.1f} | "
            f"{r['t_analysis']:.2f} | {r['iterations']} | {r['rss']:.0f} | {r['eq3']:.1e} | "
            + dense_cells(r, dense.get(r["n"])) + " |")
    lines += method_table(rows, krylov, timeout)
    lines += ["", "## Physics of the same runs (1 rank)", "",
              "| N | L-scaled f minimum c (all / without localised) | localised | "
              "q'/q at e0 = 0.05, 0.1, 0.2, 0.3, 0.4 | omega_t^2 | omega_t^2 N^(2/3) | max trial "
              "energy | omega_L^2 (Eq. kkk) | modes below sqrt(2) omega_t (need q'/2) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["ranks"] != 1:
            continue
        fr = ", ".join(f"{x[1]:.2f}" for x in r["fractions"])
        lines.append(f"| {r['n']} | {r['c']:.2f} / {r['c_nt']:.2f} | {r['localised']} | {fr} | "
                     f"{r['omega_t2']:.4f} | {r['omega_t2'] * r['n'] ** (2 / 3):.2f} | "
                     f"{r['E_max']:.3f} | {r['omega_L2']:.2f} | {r['n_below']} "
                     f"({r['q_prime'] / 2:g}) |")
    lines += ["", "f(x) (10 slabs, x/L from the plane):", ""]
    for r in rows:
        if r["ranks"] == 1:
            lines.append(f"- N = {r['n']}: " + " ".join(f"{x[1]:.2f}" for x in r["f"]))
    return "\n".join(lines) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 16384])
    p.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    p.add_argument("--dense-max", type=int, default=4096,
                   help="largest N for the dense baseline (memory ~ 3 (3N)^2 doubles)")
    p.add_argument("--dense-vectors-max", type=int, default=1024,
                   help="largest N for which the baseline also computes the null basis and "
                   "compares subspaces; above it the baseline only counts (singular values)")
    p.add_argument("--krylov-timeout", type=float, default=600.0,
                   help="stop the 1-rank SLEPc Krylov-Schur comparison after this many s (600)")
    p.add_argument("--conditions", default="not stated",
                   help="what else ran on the machine, for the page")
    p.add_argument("--workdir", default=os.path.join(ROOT, "bench-out"))
    p.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-softmodes.md"))
    args = p.parse_args()
    os.makedirs(args.workdir, exist_ok=True)
    rows, dense, krylov = [], {}, {}
    for n in args.sizes:
        path = ensure_packing(args.workdir, n)
        for ranks in args.ranks:
            r = dict(run_parjam(path, n, ranks, args.workdir,
                                vectors=(ranks == 1 and n <= args.dense_vectors_max)), n=n)
            print(json.dumps({k: v for k, v in r.items() if k not in ("f", "fractions")}),
                  flush=True)
            rows.append(r)
        if 1 in args.ranks:
            krylov[n] = run_parjam(path, n, 1, args.workdir, False, "krylov",
                                   args.krylov_timeout)
            kr = krylov[n]
            print(f"krylov N = {n}: " + (f"{kr['t_null']:.1f} s, count {kr['count']}" if kr
                                         else f"stopped after {args.krylov_timeout:.0f} s"),
                  flush=True)
            assert kr is None or kr["count"] == rows[-len(args.ranks)]["count"]
        if n <= args.dense_max:
            basis = (os.path.join(args.workdir, f"soft{n}_r1_block.h5")
                     if n <= args.dense_vectors_max else None)
            dense[n] = run_dense(path, basis)
            print(f"dense N = {n}: {json.dumps(dense[n])}", flush=True)
            assert dense[n]["count"] == rows[-1]["count"], "dense and parjam counts differ"
    host = f"{os.cpu_count()} cores, {os.uname().sysname} {os.uname().release}"
    with open(args.out, "w") as fh:
        fh.write(markdown(rows, dense, host, args.conditions, krylov, args.krylov_timeout))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
