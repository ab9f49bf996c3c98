"""Elastic moduli by linear response: ``parjam moduli`` (CG on the translation-free subspace,
preconditioned by a MUMPS Cholesky factor on one rank by default) on 1 and 2 ranks, per variant
of the preconditioner (GAMG, block Jacobi + ICC, hypre, ...).

Limit: the linear algebra alone, the preconditioner's set-up (a factorisation) plus the
d(d+1)/2 solves, read from ``-log_view`` (PCSetUp + KSPSolve); the rest of the solve stage is
assembly.  Peer: scipy's SuperLU of the same dynamical matrix built by the numpy peer from the
file (particle 0 pinned, which removes the translations), solved for the affine force fields
of the d^2 strains.  Check: the non-affine part of the energy tensor, c_affine - c_energy =
Xi^T D^+ Xi / V (paper Section IV), against the peer's, relative to its largest entry.
"""

import os
import time

import h5py
import numpy as np
import scipy.sparse.linalg as spl

from benchmarks import harness, reference

# 2D, dphi = 0.1: stable in its box, and so are its tiled copies
STABLE = "tests/data/lengths_d2_N1024_dphi1e-01.h5"
TITLE = "parjam moduli against its factorisation and solves, and scipy SuperLU"
QUICK = {"packings": ["tests/data/ref_d3_mono_N128_dphi1e-03.h5"], "ranks": [1],
         "variant": ["default:", "GAMG: -moduli_pc_type gamg"]}


def add_arguments(ap):
    ap.add_argument("--packings", nargs="+", default=[STABLE + ":3", STABLE + ":6"],
                    help="packing files, PATH:K for PATH tiled K^d times (stable in its box: "
                    "CG needs a positive semi-definite D)")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--variant", nargs="+", default=[
        "default:", "GAMG: -moduli_pc_type gamg",
        "bjacobi + ICC(0): -moduli_pc_type bjacobi -moduli_sub_pc_type icc"],
        help="LABEL: PETSc options of the moduli solver")
    ap.add_argument("--scipy-max", type=int, default=20000, help="largest N' for SuperLU")
    ap.add_argument("--timeout", type=float, default=3600)


def peer(path, spec):
    """The peer's row and its non-affine tensor Xi^T D^+ Xi / V (d^2 x d^2)."""
    net = reference.Network.read(path)
    t0 = time.perf_counter()
    D = net.hessian("full").tocsc()
    X = net.strain_forces().T
    d = net.d
    lu = spl.splu(D[d:, d:].tocsc())
    factor = time.perf_counter() - t0
    U = np.zeros_like(X)
    U[d:] = lu.solve(np.ascontiguousarray(X[d:]))
    Q = X.T @ U / net.L ** d
    row = {"packing": harness.label(spec), "n_active": net.size, "variant": "scipy SuperLU",
           "tree": "-", "ranks": 1, "setup_s": factor, "solve_s": time.perf_counter() - t0
           - factor, "fill": lu.L.nnz + lu.U.nnz}
    return row, Q


def run(args, trees, work):
    rows = []
    for spec in args.packings:
        path = harness.packing(spec, work)
        ref, Q = None, None
        if reference.Network.read(path).size <= args.scipy_max:
            ref, Q = peer(path, spec)
            rows.append(ref)
        for label, opts in harness.variants(args.variant):
            for tree_label, tree in trees:
                for ranks in args.ranks:
                    out = os.path.join(work, f"moduli-{len(rows)}.h5")
                    res = harness.run(["parjam", "moduli", path, "--out", out, "-q", *opts,
                                       "-log_view", ":" + out + ".log"], ranks, tree,
                                      args.timeout)
                    row = {"packing": harness.label(spec), "variant": label,
                           "tree": tree_label, "ranks": ranks, **res.measured()}
                    if not res.ok:
                        rows.append(dict(row, error=res.error))
                        continue
                    with h5py.File(out, "r") as f:
                        g = f["moduli"]
                        nonaffine = g["c_affine"][()] - g["c_energy"][()]
                        row.update(n_active=int(g.attrs["N_active"]), B=float(g.attrs["B"]),
                                   G=float(g.attrs["G"]), pc=str(g["solver"].attrs["pc_type"]),
                                   max_residual=float(g.attrs["max_residual"]),
                                   iterations=int(g["solver/iterations"][()].max()))
                    stages, ev = harness.log_view(out + ".log")
                    row.update(setup_s=ev.get("PCSetUp", (0, 0.0))[1],
                               solve_s=ev.get("KSPSolve", (0, 0.0))[1],
                               stage_s=stages.get("moduli: solve", 0.0)
                               + stages.get("moduli: assemble", 0.0))
                    if Q is not None:
                        row["diff"] = float(np.abs(nonaffine.reshape(Q.shape) - Q).max()
                                            / np.abs(Q).max())
                        row["peer_ratio"] = (ref["setup_s"] + ref["solve_s"]) / max(
                            row["setup_s"] + row["solve_s"], 1e-12)
                    rows.append(row)
    return rows


COLUMNS = [
    ("packing", "packing", ""), ("N'", "n_active", "d"), ("variant", "variant", ""),
    ("PC", "pc", ""), ("tree", "tree", ""), ("ranks", "ranks", "d"),
    ("wall s", "seconds", ".1f"), ("assemble + solve stages s", "stage_s", ".3g"),
    ("set-up s", "setup_s", ".3g"), ("solves s", "solve_s", ".3g"),
    ("iterations (max)", "iterations", "d"), ("max residual", "max_residual", ".1e"),
    ("SuperLU fill", "fill", ".3g"),
    ("scipy / parjam (set-up + solves)", "peer_ratio", ".1f"),
    ("non-affine rel. diff vs scipy", "diff", ".1e"), ("B", "B", ".6g"), ("G", "G", ".6g"),
    ("peak MB/rank", "peak_mb", ".0f"), ("error", "error", "")]


def notes(rows):
    return ["set-up: PCSetUp (for the default, the MUMPS factorisation), solves: KSPSolve of "
            "the d(d+1)/2 strains, both from `-log_view` (largest rank); for scipy, splu and "
            "the d^2 solves.  The difference column compares c_affine - c_energy of the output "
            "file with the peer's Xi^T D^+ Xi / V."]
