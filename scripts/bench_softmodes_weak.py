#!/usr/bin/env python3
"""Weak scaling of one soft-mode cut (``parjam softmodes --cut x=0.5``, 3D) at a fixed number
of particles per rank, P = 1, 2, 4 (8) ranks (oversubscribed is fine: memory is the point):
main's code (``git archive BASE parjam``, the serial cut system on a whole packing read by every
rank) against this checkout's (the cut system on the distributed active network, each rank
reading its rows), side by side in one run.  Run by hand, never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_softmodes_weak.py [--ranks 1 2 4] [--per-rank 4096]
        [--base 2d1be98] [--out docs/bench-softmodes-weak.md]

Packings: tests/data's 3D packings tiled k x k x k by scripts/tile_packing.py so that
N = per_rank x P (4096 per rank: 512 x 2^3, 128 x 4^3, 256 x 4^3, 512 x 4^3; 2048 per rank:
256 x 2^3, 512 x 2^3, 128 x 4^3, 256 x 4^3), made under bench-out/weak when missing.  They are
a few contacts from isostatic (analysed with --allow-hyperstatic).

Each (P, code) is one ``mpirun -n P`` of a small driver that runs the library the command runs
(read, cut, ``softmodes.analyze``; no output file) and prints every rank's peak resident set
(getrusage ru_maxrss) after the cut is prepared ("before"), after the inertia count, after the
null basis, and at the end.  The basis is N' d n_soft 8 B over the ranks: with q ~ L^(d-1) it
grows as P^(2/3) per rank at fixed N/P, so the page reports it apart from the rest (peak -
basis share), which is what should stay flat.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHON = os.path.join(ROOT, ".venv", "bin", "python")
DATA = os.path.join(ROOT, "tests", "data")
TILES = {4096: {1: ("soft_d3_N512_m0", 2), 2: ("ref_d3_mono_N128_dphi1e-06", 4),
                4: ("soft_d3_N256_m0", 4), 8: ("soft_d3_N512_m0", 4)},
         2048: {1: ("soft_d3_N256_m0", 2), 2: ("soft_d3_N512_m0", 2),
                4: ("ref_d3_mono_N128_dphi1e-06", 4), 8: ("soft_d3_N256_m0", 4)}}

DRIVER = r"""
import json, resource, sys, time
code, path = sys.argv[1:3]
from parjam import env
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
from mpi4py import MPI
from parjam import softmodes as sm
def rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
t0 = time.perf_counter()
if code == "old":
    from parjam.files import h5md
    pack = h5md.read_packing(path)
    cs = sm.prepare(pack, [sm.Plane(0, 0.5)], allow_hyperstatic=True)
    n_local = None
else:
    from parjam.files import rowio
    net = rowio.network(comm, path)
    cs = sm.prepare(None, [sm.Plane(0, 0.5)], allow_hyperstatic=True, net=net)
    n_local = cs.n_local
marks = {"before": rss()}
t1 = time.perf_counter()
stages = []
res = sm.analyze(comm, cs, 0.1, 10, lambda msg: stages.append(rss()))
t2 = time.perf_counter()
marks.update(count=stages[0], basis=stages[1], peak=rss())
mpi = MPI.COMM_WORLD
rows = mpi.gather({"rank": mpi.Get_rank(), "n_local": n_local, **marks}, root=0)
if mpi.Get_rank() == 0:
    print("RESULT " + json.dumps({
        "ranks": rows, "n": int(cs.n_total), "n_active": int(cs.n), "q": int(cs.q),
        "count": int(res.count), "n_soft": int(res.n_soft), "seconds_prepare": t1 - t0,
        "seconds_analyze": t2 - t1, "e": res.e.tolist(), "f": res.overlap[:, 1].tolist()}))
"""


def packing(per_rank, p, outdir):
    src, k = TILES[per_rank][p]
    path = os.path.join(outdir, f"t{per_rank * p}.h5")
    if not os.path.exists(path):
        subprocess.run([PYTHON, os.path.join(ROOT, "scripts", "tile_packing.py"),
                        os.path.join(DATA, src + ".h5"), str(k), path], check=True)
    return path, f"{src} x {k}^3"


def old_tree(base, tmp):
    """main's parjam package, unpacked from git into ``tmp`` (the checkout is not touched)."""
    archive = subprocess.run(["git", "-C", ROOT, "archive", base, "parjam"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
    return tmp


def run(code, path, p, pythonpath, timeout):
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    env = dict(os.environ, PYTHONPATH=pythonpath, OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1", OMPI_MCA_rmaps_base_oversubscribe="1")
    out = subprocess.run(mpirun + ["-n", str(p), PYTHON, "-c", DRIVER, code, path],
                         capture_output=True, text=True, env=env, cwd="/tmp", timeout=timeout)
    if out.returncode:  # recorded, not hidden: the page shows the error line
        errors = [ln.strip() for ln in out.stderr.splitlines() if "Error" in ln]
        return {"failed": errors[-1] if errors else out.stderr[-300:]}
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def page(res, ranks, per_rank, made, base):
    d = 3
    lines = [
        "# Benchmark: weak scaling of one soft-mode cut on the distributed network",
        "",
        "Made by `scripts/bench_softmodes_weak.py` (run by hand; see its docstring). One plane "
        f"x = L/2 in 3D packings of N = {per_rank} x P particles (tiled from tests/data: "
        + "; ".join(f"P = {p}: {made[p]}" for p in ranks) + "), the whole analysis of "
        "`parjam softmodes` (inertia count, null basis by block inverse iteration in 64-column "
        "blocks, Eq. 3 check, extension, f(x), trial modes, variational count), no output "
        f"file. `old` is main at {base} (the whole packing read and cut on every rank), `new` "
        "this branch (the cut system on parjam.net.active, each rank reading its own rows). "
        "Ranks oversubscribed on a 2-core machine shared with other jobs: times are "
        "indicative only. Memory is the peak resident set (getrusage ru_maxrss, MB) of each "
        "rank: `before` after the cut system is made, `count` after the MUMPS inertia "
        "counts (`count - before`: the MUMPS LDL^T factor of the inertia count), `peak` at the "
        "end; `basis` = N' d n_soft 8 B / P (the basis is split over the ranks by rows and is "
        "N'/P x n_soft per rank), `rest` = peak - basis, `rest - factor` = rest - (count - "
        "before): what is neither the basis nor a MUMPS factor (the null-space solve holds one "
        "factor of M + tau k I of about the inertia factor's size).",
        "",
        "| P | N | N' | q | n_soft | code | before MB (max rank) | before / P=1 | count - "
        "before MB (max rank) | peak MB (min..max rank) | basis MB/rank | rest MB (max rank) | "
        "rest / P=1 | rest - factor MB | (rest - factor) / P=1 | prepare s | analyze s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    first = {}
    for p in ranks:
        for code in ("old", "new"):
            r = res[(p, code)]
            if "failed" in r:
                lines.append(f"| {p} | | | | | {code} | failed: {r['failed']} |")
                continue
            peaks = [x["peak"] for x in r["ranks"]]
            basis = r["n_active"] * d * r["n_soft"] * 8 / 2**20 / p
            rest = max(peaks) - basis
            before = max(x["before"] for x in r["ranks"])
            factor = max(x["count"] - x["before"] for x in r["ranks"])
            first.setdefault(code, (rest, before, rest - factor))
            lines.append(
                f"| {p} | {r['n']} | {r['n_active']} | {r['q']} | {r['n_soft']} | {code} | "
                f"{before:.0f} | {before / first[code][1]:.3f} | "
                f"{factor:.0f} | {min(peaks):.0f}..{max(peaks):.0f} | {basis:.0f} | "
                f"{rest:.0f} | {rest / first[code][0]:.2f} | {rest - factor:.0f} | "
                f"{(rest - factor) / first[code][2]:.2f} | {r['seconds_prepare']:.1f} | "
                f"{r['seconds_analyze']:.1f} |")
    lines += ["", "new / old at each P (max rank): before, peak, rest:", ""]
    ok = [p for p in ranks if "failed" not in res[(p, "old")] and "failed" not in
          res[(p, "new")]]
    for p in ok:
        o, n = res[(p, "old")], res[(p, "new")]
        ob, nb = (max(x["before"] for x in r["ranks"]) for r in (o, n))
        op, np_ = (max(x["peak"] for x in r["ranks"]) for r in (o, n))
        basis = n["n_active"] * d * n["n_soft"] * 8 / 2**20 / p
        lines.append(f"- P = {p}: before {nb / ob:.2f}, peak {np_ / op:.2f}, rest "
                     f"{(np_ - basis) / (op - basis):.2f}")
    lines += ["", "Agreement old against new (count equal; max |difference| of the extension "
              "spectrum e and of f(x)):", ""]
    for p in ok:
        o, n = res[(p, "old")], res[(p, "new")]
        same = "equal" if o["count"] == n["count"] else "DIFFERENT"
        de = np.abs(np.subtract(o["e"], n["e"])).max()
        df = np.abs(np.subtract(o["f"], n["f"])).max()
        lines.append(f"- P = {p}: count {same} ({n['count']}), |de| {de:.1e}, |df| {df:.1e}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--per-rank", type=int, default=4096, choices=sorted(TILES))
    ap.add_argument("--base", default="2d1be98", help="main's commit (the old code)")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-softmodes-weak.md"))
    ap.add_argument("--reuse", action="store_true",
                    help="keep the (P, code) pairs already in bench-out/weak/results-N.json "
                    "(both codes of a P are always run together)")
    args = ap.parse_args(argv)
    outdir = os.path.join(ROOT, "bench-out", "weak")
    os.makedirs(outdir, exist_ok=True)
    store = os.path.join(outdir, f"results-{args.per_rank}.json")
    saved = {}
    if args.reuse and os.path.exists(store):
        with open(store) as fh:
            saved = {int(k): v for k, v in json.load(fh).items()
                     if not any("failed" in r for r in v.values())}  # failed: run again
    res, made = {}, {}
    with tempfile.TemporaryDirectory(prefix="parjam-weak-") as tmp:
        old = old_tree(args.base, tmp)
        for p in args.ranks:
            path, made[p] = packing(args.per_rank, p, outdir)
            if p in saved:
                res[(p, "old")], res[(p, "new")] = saved[p]["old"], saved[p]["new"]
                continue
            for code in ("old", "new"):
                res[(p, code)] = r = run(code, path, p, old if code == "old" else ROOT,
                                         args.timeout)
                print(f"P={p} {code}: " + (r["failed"] if "failed" in r else
                      f"N'={r['n_active']} n_soft={r['n_soft']} peak "
                      f"{max(x['peak'] for x in r['ranks']):.0f} MB, "
                      f"{r['seconds_analyze']:.1f} s"), flush=True)
            saved[p] = {"old": res[(p, "old")], "new": res[(p, "new")]}
            with open(store, "w") as fh:
                json.dump(saved, fh)
    text = page(res, args.ranks, args.per_rank, made, args.base)
    with open(args.out, "w") as fh:
        fh.write(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
