"""The soft modes of one cut: ``parjam softmodes --cut x=0.5`` (MUMPS inertia count, null basis
by block inverse iteration in column blocks) on 1 and 2 ranks, per variant (the basis out of
core, SLEPc Krylov-Schur instead of the blocks, ...).

Limit (memory): the basis itself, N' d n_basis doubles over the ranks; the peak per rank over
it is what the solver holds besides (factors, work blocks).  Peer: the dense LAPACK SVD of the
cut rigidity matrix (paper Eq. 3: the null space of S is the soft modes), what a numpy
reference implementation does, built from the file's contacts minus the cut ones the output
file lists.  Check: its null-space dimension against parjam's count, and parjam's Eq. 3
residual.
"""

import os
import time

import h5py
import numpy as np

from benchmarks import harness, reference

TITLE = "parjam softmodes (one cut) against its basis size and a dense SVD"
QUICK = {"packings": ["tests/data/soft_d3_N256_m0.h5"], "ranks": [1],
         "variant": ["columns:", "out of core: --scratch {work}"]}


def add_arguments(ap):
    ap.add_argument("--packings", nargs="+", default=["tests/data/soft_d3_N512_m0.h5",
                                                      "tests/data/soft_d3_N512_m0.h5:2"],
                    help="near-isostatic packing files, PATH:K for PATH tiled K^d times")
    ap.add_argument("--cut", default="x=0.5")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--variant", nargs="+", default=[
        "columns:", "out of core: --scratch {work}", "Krylov-Schur: --basis krylov"],
        help="LABEL: softmodes arguments ({work}: the scratch directory)")
    ap.add_argument("--dense-max", type=int, default=2048, help="largest N' for the dense SVD")
    ap.add_argument("--timeout", type=float, default=3600)


def dense_count(path, cut_contacts):
    """(null-space dimension of the cut rigidity matrix by numpy's SVD, seconds)."""
    net = reference.Network.read(path)
    cut = {tuple(c) for c in np.sort(cut_contacts, axis=1).tolist()}
    drop = np.array([tuple(p) in cut for p in np.sort(net.pairs, axis=1).tolist()])
    t0 = time.perf_counter()
    s = np.linalg.svd(net.rigidity(drop).toarray(), compute_uv=False)
    rank = int(np.count_nonzero(s > 1e-8 * s[0]))
    return net.size * net.d - rank, time.perf_counter() - t0


def run(args, trees, work):
    rows, floor = [], {}
    for spec in args.packings:
        path = harness.packing(spec, work)
        dense = None
        for label, extra in harness.variants(args.variant):
            extra = [a.replace("{work}", work) for a in extra]
            for tree_label, tree in trees:
                for ranks in args.ranks:
                    out = os.path.join(work, f"soft-{len(rows)}.h5")
                    res = harness.run(["parjam", "softmodes", path, "--cut", args.cut,
                                       "--allow-hyperstatic", "--out", out, "-q", *extra],
                                      ranks, tree, args.timeout)
                    row = {"packing": harness.label(spec), "variant": label,
                           "tree": tree_label, "ranks": ranks, **res.measured()}
                    if not res.ok:
                        rows.append(dict(row, error=res.error))
                        continue
                    with h5py.File(out, "r") as f:
                        g, c = f["softmodes"], f["softmodes/count"].attrs
                        row.update(n_active=int(c["N_active"]), q=int(c["q"]),
                                   count=int(g["count"][()]), n_basis=int(c["n_basis"]),
                                   d=int(c["trivial"]),
                                   eq3=float(c["eq3_residual"]),
                                   count_s=float(g.attrs["seconds_count"]),
                                   basis_s=float(g.attrs["seconds_null_space"]),
                                   analysis_s=float(g.attrs["seconds_analysis"]))
                        cut = g["cut_contacts"][()]
                    row["basis_mb"] = (row["n_active"] * row["d"] * row["n_basis"] * 8 / 2**20
                                       / ranks)
                    if (tree, ranks) not in floor:
                        floor[(tree, ranks)] = harness.floor_mb(ranks, tree)
                    row["extra_mb"] = row["peak_mb"] - floor[(tree, ranks)]
                    if dense is None and row["n_active"] <= args.dense_max:
                        dense = dense_count(path, cut)
                        rows.append({"packing": row["packing"], "variant": "dense SVD",
                                     "tree": "-", "ranks": 1, "n_active": row["n_active"],
                                     "q": row["q"], "count": dense[0], "count_s": dense[1]})
                    if dense is not None:
                        row["dense_count"] = dense[0]
                    rows.append(row)
    return rows


COLUMNS = [
    ("packing", "packing", ""), ("N'", "n_active", "d"), ("q", "q", "d"),
    ("variant", "variant", ""), ("tree", "tree", ""), ("ranks", "ranks", "d"),
    ("wall s", "seconds", ".1f"), ("count s", "count_s", ".2f"), ("basis s", "basis_s", ".2f"),
    ("analysis s", "analysis_s", ".2f"), ("null space", "count", "d"),
    ("dense SVD", "dense_count", "d"), ("Eq. 3 residual", "eq3", ".1e"),
    ("peak MB/rank", "peak_mb", ".0f"), ("peak - floor MB/rank", "extra_mb", ".0f"),
    ("basis MB/rank", "basis_mb", ".1f"),
    ("(peak - floor) / basis", lambda r: r["extra_mb"] / r["basis_mb"] if r.get("basis_mb")
     else None, ".1f"), ("error", "error", "")]


def notes(rows):
    return ["count, basis, analysis s: the command's own stage times (`/softmodes` attributes); "
            "dense SVD: its count s is numpy's singular values of the cut S (count only); floor: "
            "the peak of a process that only starts parjam, PETSc and MPI; basis MB/rank: "
            "N' d n_basis doubles over the ranks; null "
            "space: d + q - 1 - (Nc - Nc_iso), translations included."]
