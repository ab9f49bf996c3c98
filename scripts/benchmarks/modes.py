"""The lowest modes of the dynamical matrix: ``parjam modes --method sinvert`` (SLEPc
Krylov-Schur, shift-and-invert with a MUMPS LDL^T, translations deflated) on 1 and 2 ranks, per
variant of PETSc options (ncv, tolerance, factorisation package, ...), and spectrum slicing of
the lowest part of the spectrum.

Limit: one factorisation (symbolic + numeric) plus 2k triangular solves at the measured cost
per solve (``-log_view``); EPSSolve / limit says how much more the eigensolver spends.
Peers: scipy.sparse.linalg.eigsh in shift-invert mode (SuperLU; k + d eigenvalues, the d
translations dropped) and numpy's dense eigvalsh (every eigenvalue: the reference) of the same
matrix built by the numpy peer from the file.  Check: the largest relative difference of the
k eigenvalues from the dense ones (or from scipy's above --dense-max), and slicing's count.
"""

import os
import time

import h5py
import numpy as np
import scipy.sparse.linalg as spl

from benchmarks import harness, reference

# 2D, dphi = 0.1: stable in its box, and so are its tiled copies
STABLE = "tests/data/lengths_d2_N1024_dphi1e-01.h5"
TITLE = "parjam modes (shift-and-invert, slicing) against its factorisation, scipy and LAPACK"
QUICK = {"packings": ["tests/data/ref_d3_mono_N128_dphi1e-03.h5"], "k": 10, "ranks": [2],
         "slice": 0.1}


def add_arguments(ap):
    ap.add_argument("--packings", nargs="+", default=[STABLE, STABLE + ":4"],
                    help="packing files, PATH:K for PATH tiled K^d times (a packing stable "
                    "in its box: a tiled copy of one unstable to shear has negative modes)")
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--tol", type=float, default=1e-10)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--variant", nargs="+", default=["default:"],
                    help="LABEL: PETSc options, e.g. 'ncv 2k: -modes_eps_ncv 200'")
    ap.add_argument("--slice", type=float, default=0.0,
                    help="also slice this fraction of the spectrum (needs the dense reference)")
    ap.add_argument("--dense-max", type=int, default=4096, help="largest N' for numpy eigvalsh")
    ap.add_argument("--scipy-max", type=int, default=40000, help="largest N' for scipy eigsh")
    ap.add_argument("--timeout", type=float, default=3600)


def peers(path, spec, args):
    """Rows of scipy and numpy on the packing, and the reference eigenvalues (or None)."""
    net = reference.Network.read(path)
    H = net.hessian()
    norm = float(abs(H).sum(axis=1).max())
    base = {"packing": harness.label(spec), "n_active": net.size, "tree": "-", "ranks": 1}
    rows, ref = [], {}
    if net.size <= args.dense_max:
        t0 = time.perf_counter()
        ref["dense"] = np.linalg.eigvalsh(H.toarray())[net.d:]
        rows.append(dict(base, method="numpy eigvalsh", seconds=time.perf_counter() - t0))
    if net.size <= args.scipy_max:
        t0 = time.perf_counter()
        lam, vec = spl.eigsh(H.tocsc(), k=args.k + net.d, sigma=-1e-9 * norm, which="LM")
        seconds = time.perf_counter() - t0
        order = np.argsort(lam)[net.d:]
        ref["scipy"] = lam[order]
        res = np.linalg.norm(H @ vec[:, order] - vec[:, order] * lam[order], axis=0) / norm
        rows.append(dict(base, method="scipy eigsh", seconds=seconds, max_error=res.max()))
    truth = ref.get("dense", ref.get("scipy"))
    if "dense" in ref and "scipy" in ref:  # the reference itself has no difference to show
        rows[1]["diff"] = diff(ref["scipy"], truth)
    return rows, truth


def diff(lam, truth):
    if lam is None or truth is None:
        return None
    m = min(len(lam), len(truth))
    return float(np.max(np.abs(lam[:m] / truth[:m] - 1))) if m else None


def parjam(path, tree, ranks, what, opts, work, timeout):
    """One ``parjam modes`` run: (row, eigenvalues)."""
    out = os.path.join(work, f"modes-{os.getpid()}-{time.monotonic_ns()}.h5")
    log = out + ".log"
    res = harness.run(["parjam", "modes", path, "--matrix", "full", "--out", out, "-q", *what,
                       *opts, "-log_view", ":" + log], ranks, tree, timeout)
    row = res.measured()
    if not res.ok:  # exit 4: written, but some pairs missed the tolerance (kept in the row)
        row["error"] = res.error
        if not os.path.exists(out):
            return row, None
    with h5py.File(out, "r") as f:
        lam, err = f["modes/eigenvalue"][()], f["modes/error"][()]
        row["n_active"] = int(f["modes"].attrs["n_active"])
    _, ev = harness.log_view(log)
    solves, solve_s = ev.get("MatSolve", (0, 0.0))
    factor = ev.get("MatCholFctrSym", (0, 0.0))[1] + ev.get("MatCholFctrNum", (0, 0.0))[1]
    return dict(row, eps_s=ev.get("EPSSolve", (0, None))[1], factor_s=factor, solves=solves,
                solve_s=solve_s, max_error=float(err.max()) if len(err) else None,
                found=len(lam)), lam


def run(args, trees, work):
    rows = []
    for spec in args.packings:
        path = harness.packing(spec, work)
        base_rows, truth = peers(path, spec, args)
        rows += base_rows
        base = {"packing": harness.label(spec)}
        base.update({"n_active": base_rows[0]["n_active"]} if base_rows else {})
        for label, opts in harness.variants(args.variant):
            for tree_label, tree in trees:
                for ranks in args.ranks:
                    row, lam = parjam(path, tree, ranks, ["--k", str(args.k), "--method",
                                                          "sinvert", "--tol", str(args.tol)],
                                      opts, work, args.timeout)
                    if "eps_s" in row:
                        per = row["solve_s"] / max(row["solves"], 1)
                        row["limit_s"] = row["factor_s"] + 2 * args.k * per
                    rows.append(dict(base, **row, method=f"sinvert {label}", tree=tree_label,
                                     ranks=ranks, diff=diff(lam, truth)))
        if args.slice and base_rows and base_rows[0]["method"] == "numpy eigvalsh":
            m = int(args.slice * len(truth))
            top = float(np.sqrt(0.5 * (truth[m - 1] + truth[m])))
            for tree_label, tree in trees:
                for ranks in args.ranks:
                    part = ["-modes_eps_krylovschur_partitions", str(ranks)] if ranks > 1 else []
                    row, lam = parjam(path, tree, ranks, ["--window", f"0,{top:.12g}", "--method",
                                                          "slice", "--tol", str(args.tol)],
                                      part, work, args.timeout)
                    rows.append(dict(base, **row, method=f"slice ({m} modes)", tree=tree_label,
                                     ranks=ranks, diff=diff(lam, truth), expected=m))
    return rows


COLUMNS = [
    ("packing", "packing", ""), ("N'", "n_active", "d"), ("method", "method", ""),
    ("tree", "tree", ""), ("ranks", "ranks", "d"), ("wall s", "seconds", ".2f"),
    ("EPSSolve s", "eps_s", ".3g"), ("limit s", "limit_s", ".3g"),
    ("EPSSolve / limit", lambda r: r["eps_s"] / r["limit_s"] if r.get("limit_s") else None,
     ".2f"),
    ("factor s", "factor_s", ".3g"), ("MatSolve calls", "solves", "d"),
    ("found", "found", "d"), ("expected", "expected", "d"),
    ("max residual", "max_error", ".1e"), ("max rel. diff vs reference", "diff", ".1e"),
    ("peak MB/rank", "peak_mb", ".0f"), ("error", "error", "")]


def notes(rows):
    return ["limit: one MUMPS factorisation (MatCholFctrSym + MatCholFctrNum) + 2k MatSolve at "
            "the measured cost per solve; residual ||D v - lambda v|| / ||D||_inf; reference: "
            "numpy eigvalsh of the numpy peer's D (scipy eigsh above --dense-max); wall s of "
            "parjam includes starting the processes and reading the file."]
