"""D(omega) by the kernel polynomial method: ``parjam dos --method kpm`` for a grid of moments x
probes, on 1 and 2 ranks, against the dense spectrum of the same packing.

Limit: KPM is nothing but sparse matrix-vector products (moments / 2 per probe, plus the
Lanczos bounds): its time over the time of its MatMult calls (``-log_view``) says what the rest
costs.  Reference: every eigenvalue by numpy's dense eigvalsh of the matrix the numpy peer
builds from the file (its time beside KPM's), and D0 and omega* of that spectrum from a dense
``parjam modes`` of every mode (the definitions of docs/howto/spectra.md).  Accuracy: the L1
distance of the per-mode D(omega) on KPM's bins, the relative error of D0 and the error of
omega*.
"""

import os
import time

import h5py
import numpy as np

from benchmarks import harness, reference

TITLE = "parjam dos --method kpm against its matrix-vector products and dense LAPACK"
QUICK = {"packings": ["tests/data/ref_d3_mono_N128_dphi1e-03.h5"], "moments": [64],
         "probes": [4], "ranks": [1]}


def add_arguments(ap):
    ap.add_argument("--packings", nargs="+", default=["tests/data/lengths_d2_N1024_dphi1e-03.h5",
                                                      "tests/data/lengths_d2_N1024_dphi1e-01.h5"],
                    help="packing files, PATH:K for PATH tiled K^d times")
    ap.add_argument("--moments", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--probes", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--matrix", default="full", choices=("full", "relaxed"))
    ap.add_argument("--timeout", type=float, default=3600)


def dense(path, spec, args, work):
    """The reference row: numpy's eigenvalues (and their time), D0 and omega* by parjam dos."""
    net = reference.Network.read(path)
    t0 = time.perf_counter()
    lam = np.linalg.eigvalsh(net.hessian(args.matrix).toarray())[net.d:]
    seconds = time.perf_counter() - t0
    every = os.path.join(work, "dense.h5")
    res = harness.run(["parjam", "modes", path, "--matrix", args.matrix, "--method", "dense",
                       "--k", str(len(lam)), "--out", every, "-q"], 1, timeout=args.timeout)
    if not res.ok:
        raise SystemExit(f"bench kpm: the dense reference failed: {res.error}")
    with h5py.File(every, "r") as f:  # D0 and omega* of the whole spectrum
        d0, wstar = float(f["dos"].attrs["D0"]), float(f["dos"].attrs["omega_star"])
    return {"packing": harness.label(spec), "n_active": net.size, "method": "dense eigvalsh",
            "tree": "-", "ranks": 1, "seconds": seconds, "D0": d0, "omega_star": wstar}, lam


def run(args, trees, work):
    rows = []
    for spec in args.packings:
        path = harness.packing(spec, work)
        ref, lam = dense(path, spec, args, work)
        rows.append(ref)
        omega = np.sign(lam) * np.sqrt(np.abs(lam))
        for tree_label, tree in trees:
            for ranks in args.ranks:
                for m in args.moments:
                    for p in args.probes:
                        out = os.path.join(work, f"kpm-{tree_label}-{ranks}-{m}-{p}.h5")
                        res = harness.run(["parjam", "dos", "--method", "kpm", path, "--matrix",
                                           args.matrix, "--moments", m, "--probes", p, "--out",
                                           out, "-log_view", ":" + out + ".log"], ranks, tree,
                                          args.timeout)
                        row = dict(ref, method=f"kpm {m} x {p}", tree=tree_label, ranks=ranks,
                                   seconds=res.seconds, peak_mb=res.peak, moments=m, probes=p)
                        if not res.ok:
                            rows.append(dict(row, error=res.error, D0=None, omega_star=None))
                            continue
                        with h5py.File(out, "r") as f:
                            g = f["dos"]
                            edges, density = g["edges"][()], g["density"][()]
                            d0, wstar = float(g.attrs["D0"]), float(g.attrs["omega_star"])
                            kpm_s = float(np.sum(g.attrs["seconds"]))
                        counts, _ = np.histogram(omega, edges)
                        truth = counts / len(omega) / np.diff(edges)
                        _, ev = harness.log_view(out + ".log")
                        rows.append(dict(row, kpm_s=kpm_s, D0=d0, omega_star=wstar,
                                         matmults=ev.get("MatMult", (0, 0.0))[0],
                                         matmult_s=ev.get("MatMult", (0, 0.0))[1],
                                         L1=float(np.sum(np.abs(density - truth) *
                                                         np.diff(edges))),
                                         D0_err=abs(d0 / ref["D0"] - 1),
                                         resolution=wstar / (0.5 * np.pi * np.sqrt(lam.max())
                                                             / m),
                                         omega_star_err=abs(wstar - ref["omega_star"])))
    return rows


COLUMNS = [
    ("packing", "packing", ""), ("N'", "n_active", "d"), ("method", "method", ""),
    ("tree", "tree", ""), ("ranks", "ranks", "d"), ("wall s", "seconds", ".2f"),
    ("KPM s", "kpm_s", ".3g"), ("MatMult calls", "matmults", "d"),
    ("MatMult s", "matmult_s", ".3g"),
    ("KPM / MatMult", lambda r: r["kpm_s"] / r["matmult_s"] if r.get("matmult_s") else None,
     ".2f"),
    ("D0", "D0", ".4f"), ("omega*", "omega_star", ".4f"), ("L1 vs dense", "L1", ".3f"),
    ("D0 rel. error", "D0_err", ".3f"), ("omega* error", "omega_star_err", ".4f"),
    ("omega* / Delta omega", "resolution", ".1f"),
    ("peak MB/rank", "peak_mb", ".0f"), ("error", "error", "")]


def notes(rows):
    return ["KPM s: the command's own time of the KPM computation; MatMult: the sparse "
            "products in `-log_view` (largest rank); dense eigvalsh s: numpy on one core; L1: "
            "sum over KPM's bins of |D_KPM - D_dense| x bin width (per-mode normalisation, 2 at "
            "most); Delta omega = (pi / 2) sqrt(lambda_max) / moments, the Jackson kernel's width: "
            "KPM's omega* is biased high until it is many times Delta omega (parjam.vib.kpm_dos "
            "calls it resolved above a threshold)."]
