#!/usr/bin/env python3
"""The stability check without a factorisation against the exact inertia, old and new in one run
(docs/results/stability.md).  Run by hand, never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_stability.py states --dir DIR [--phi-n 4096 8192 ...]
        [--tiles 2 3 4]
    .venv/bin/python scripts/bench_stability.py check DIR/*.h5 [--ranks 1 2] [--repeats 3]
        --out bench-out/stability-check.jsonl
    .venv/bin/python scripts/bench_stability.py weak --dir DIR [--per-rank 12000]
        [--ranks 1 2 4 8] [--repeats 3] [--methods lanczos] [--baseline COMMIT]
        --out bench-out/stability-weak.jsonl
    .venv/bin/python scripts/bench_stability.py census STATES.npz ... --out bench-out/census.jsonl
    .venv/bin/python scripts/bench_stability.py report bench-out/stability-*.jsonl

states: the benchmark packings, 3D monodisperse harmonic: tests/data/soft_d3_N512_m0.h5 (near
jamming, p = 1.4e-8) tiled k x k x k (scripts/tile_packing.py), and ``parjam pack --phi 0.70
--n N --seed 1`` quenches (far from jamming); ``weak`` needs N = per-rank x P of the latter.
check: every (file, P, method) is a fresh process on P ranks (``-stability_method inertia`` or
``lanczos``), the methods interleaved, each repeated; per run the wall and CPU seconds of the
check alone, the resident set once the network is built (``before``) and its peak (getrusage
ru_maxrss) on every rank, the verdict, the count, the Lanczos steps and its failure bound.
weak: ``parjam pack --from FILE --phi 0.70`` (the state re-minimised, checked and written: the
memory of the whole command) on P ranks at N = per-rank x P, both methods interleaved, peak RSS
per rank by the benchmarks' memory wrapper (scripts/benchmarks/harness.py); with --baseline
that commit's tree (a git worktree) runs beside this one, the two interleaved.
census: both checks on states saved as .npz (x, ids, diam, L, alpha, eps and the verdict of the
run that saved them, e.g. every state the packing protocol checked), one JSON line per state.
The machine is shared: every record carries the load average at its start.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from benchmarks.harness import describe, mpirun, run as harness_run  # noqa: E402
from benchmarks.harness import trees as harness_trees  # noqa: E402

PYTHON = os.path.join(ROOT, ".venv", "bin", "python")
SMALL = os.path.join(ROOT, "tests", "data", "soft_d3_N512_m0.h5")
METHODS = ("inertia", "lanczos")

CHILD = r"""
import json, resource, sys, time
from parjam import env; from parjam.files import h5md; from parjam.pack import jamnet, stability
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
mpi = comm.tompi4py()
def rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
pack = h5md.read_packing(sys.argv[1])
net = jamnet.from_packing(mpi, pack)
before = rss()
mpi.Barrier()
t0, c0 = time.perf_counter(), cpu()
cur = stability.check(comm, net)
sec, cs = time.perf_counter() - t0, cpu() - c0
rows = mpi.gather((before, rss(), cs))
if mpi.rank == 0:
    print("RESULT " + json.dumps({
        "n": pack.n, "n_active": net.n_active, "before": [r[0] for r in rows],
        "peak": [r[1] for r in rows], "cpu": [r[2] for r in rows], "seconds": sec,
        "negative": cur.n_negative, "excess": cur.excess, "stable": int(cur.stable),
        "decided_by": cur.method, "steps": cur.steps, "failure": cur.failure,
        "lowest": cur.lowest, "shift": cur.shift, "why": cur.why}))
"""


def load():
    return os.getloadavg()[0]


def measured(ranks, argv, what, tree=ROOT):
    """Peak RSS per rank (MB), seconds and the run of ``argv`` on ``ranks`` ranks, each rank
    under the benchmarks' memory wrapper (scripts/benchmarks/harness.py), ``tree``'s parjam;
    a run without a memory report ends the benchmark, naming ``what``."""
    res = harness_run(argv, ranks=ranks, tree=tree)
    if not res.rss_mb:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{what}: no memory report ({res.error})")
    return res.rss_mb, res.seconds, res


def child(path, ranks, method, extra=()):
    """One check of ``path`` on ``ranks`` ranks by ``method`` in a fresh process."""
    opts = " ".join([f"-stability_method {method}", *extra])
    env = dict(os.environ, PETSC_OPTIONS=opts, OMP_NUM_THREADS="1")
    cmd = [PYTHON, "-c", CHILD, path]
    if ranks > 1:
        cmd = mpirun() + ["-n", str(ranks)] + cmd
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    line = [x for x in res.stdout.splitlines() if x.startswith("RESULT ")]
    if res.returncode or not line:
        sys.stderr.write(res.stdout[-3000:] + res.stderr[-3000:])
        raise SystemExit(f"check of {path} on {ranks} rank(s) by {method} failed")
    return json.loads(line[0][7:])


def cmd_states(args):
    os.makedirs(args.dir, exist_ok=True)
    for k in args.tiles:
        out = os.path.join(args.dir, f"tiled{k}.h5")
        if not os.path.exists(out):
            subprocess.run([PYTHON, os.path.join(ROOT, "scripts", "tile_packing.py"), SMALL,
                            str(k), out], check=True)
    for n in args.phi_n:
        out = os.path.join(args.dir, f"phi070_N{n}.h5")
        if os.path.exists(out):
            continue
        with tempfile.TemporaryDirectory(prefix="parjam-bench-", dir=args.dir) as tmp:
            subprocess.run([PYTHON, "-m", "parjam", "pack", "--phi", "0.70", "--n", str(n),
                            "--seed", "1", "--out", tmp, "-q"], check=True)
            made = [f for f in os.listdir(tmp) if f.endswith(".h5")]
            os.replace(os.path.join(tmp, made[0]), out)
        print(f"{out}: made", flush=True)


def cmd_check(args):
    with open(args.out, "a") as fh:
        for rep in range(args.repeats):
            for path in args.files:
                for p in args.ranks:
                    order = args.methods if (rep + p) % 2 == 0 else args.methods[::-1]
                    for method in order:
                        ld = load()
                        rec = child(path, p, method, args.petsc)
                        rec.update({"kind": "check", "file": os.path.basename(path),
                                    "ranks": p, "method": method, "repeat": rep, "load": ld})
                        fh.write(json.dumps(rec) + "\n")
                        fh.flush()
                        print(f"{rec['file']} N={rec['n']} P={p} {method}: "
                              f"{rec['seconds']:.1f} s (cpu {max(rec['cpu']):.1f}), peak "
                              f"{max(rec['peak']):.0f} MB (before {max(rec['before']):.0f}), "
                              f"stable {rec['stable']} neg {rec['negative']} "
                              f"[{rec['decided_by']}, {rec['steps']} steps], load {ld:.1f}",
                              flush=True)


def cmd_weak(args):
    with harness_trees(args.baseline) as code, open(args.out, "a") as fh:
        for rep in range(args.repeats):
            for p in args.ranks:
                n = args.per_rank * p
                src = os.path.join(args.dir, f"phi070_N{n}.h5")
                order = args.methods if (rep + p) % 2 == 0 else args.methods[::-1]
                runs = [(label, tree, m) for m in order
                        for label, tree in (code if rep % 2 == 0 else code[::-1])]
                for label, tree, method in runs:
                    with tempfile.TemporaryDirectory(prefix="parjam-weak-") as tmp:
                        ld = load()
                        argv = ["parjam", "pack", "--from", src, "--phi", "0.70", "--out", tmp,
                                "-q", "--force", "-stability_method", method]
                        mb, secs, res = measured(p, argv, f"pack N={n} P={p} {method}", tree)
                        if res.returncode:
                            sys.stderr.write(res.stderr[-3000:])
                            raise SystemExit(f"pack N={n} P={p} {method} ({label}) failed")
                    rec = {"kind": "weak", "n": n, "ranks": p, "method": method, "repeat": rep,
                           "peak": mb, "seconds": secs, "load": ld, "tree": label,
                           "commit": describe(tree)}
                    fh.write(json.dumps(rec) + "\n")
                    fh.flush()
                    print(f"weak N={n} P={p} {method} {label}: peak/rank {max(mb):.0f} MB "
                          f"(median {np.median(mb):.0f}), {secs:.0f} s, load {ld:.1f}",
                          flush=True)


def cmd_census(args):
    from parjam import env
    from parjam.pack import jamnet, stability

    comm = env.petsc().COMM_WORLD
    lanczos = stability.Settings("lanczos", exact_max_dof=0,
                                 lanczos=stability.lowest.Settings.from_options(
                                     stability.PREFIX))
    with open(args.out, "a") as fh:
        for path in args.states:
            z = np.load(path)
            st = jamnet.slab_state(comm.tompi4py(), z["x"], z["diam"], z["ids"], float(z["L"]))
            net = jamnet.network(st, float(z["alpha"]), float(z["eps"]))
            ld = load()
            t = time.perf_counter()
            new = stability.check(comm, net, lanczos)
            t_new = time.perf_counter() - t
            t = time.perf_counter()
            old = stability.check(comm, net, stability.Settings("inertia"))
            t_old = time.perf_counter() - t
            rec = {"kind": "census", "state": os.path.basename(path), "n": int(len(z["ids"])),
                   "n_active": net.n_active, "excess": net.excess,
                   "old_negative": old.n_negative, "old_stable": int(old.stable),
                   "new_negative": new.n_negative, "new_stable": int(new.stable),
                   "new_method": new.method, "lowest": new.lowest, "steps": new.steps,
                   "failure": new.failure, "why": new.why, "shift": new.shift,
                   "saved_negative": int(z["n_negative"]) if "n_negative" in z else None,
                   "seconds_new": t_new, "seconds_old": t_old, "load": ld}
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            same = "same" if (old.stable, old.n_negative > 0) == (new.stable,
                                                                  new.n_negative > 0) else "DIFF"
            print(f"{rec['state']}: old {old.n_negative} new {new.n_negative} "
                  f"({new.method}, {new.steps} steps, lowest {new.lowest:.2e}) excess "
                  f"{net.excess}: {same}", flush=True)


def median(xs):
    return float(np.median(xs)) if len(xs) else float("nan")


def cmd_report(args):
    recs = [json.loads(x) for p in args.files for x in open(p) if x.strip()]
    checks = [r for r in recs if r["kind"] == "check"]
    if checks:
        print("| packing | N | dof | P | method | decided by | verdict (negative) | steps | "
              "wall s (median) | CPU s per rank (median) | before MB | peak MB per rank "
              "(median of the largest) | check's own MB | runs | load |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        keys = sorted({(r["file"], r["n"], r["ranks"], r["method"]) for r in checks},
                      key=lambda k: (k[1], k[0], k[2], k[3]))
        for f, n, p, m in keys:
            g = [r for r in checks if (r["file"], r["n"], r["ranks"], r["method"]) ==
                 (f, n, p, m)]
            peak = median([max(r["peak"]) for r in g])
            before = median([max(r["before"]) for r in g])
            verdicts = sorted({f"{'stable' if r['stable'] else 'unstable'} "
                               f"({r['negative']})" for r in g})
            by = sorted({r["decided_by"] for r in g})
            print(f"| {f} | {n} | {3 * g[0]['n_active']} | {p} | {m} | {', '.join(by)} | "
                  f"{', '.join(verdicts)} | {median([r['steps'] for r in g]):.0f} | "
                  f"{median([r['seconds'] for r in g]):.1f} | "
                  f"{median([max(r['cpu']) for r in g]):.1f} | {before:.0f} | {peak:.0f} | "
                  f"{peak - before:.0f} | {len(g)} | "
                  f"{min(r['load'] for r in g):.0f}-{max(r['load'] for r in g):.0f} |")
    weak = [r for r in recs if r["kind"] == "weak"]
    if weak:
        print("\n| P | N | method | tree | peak RSS per rank, MB (median over runs of the largest "
              "rank) | / P = 1 | median rank, MB | wall s (median) | runs | load |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        base = {}
        labels = sorted({r.get("tree", "new") for r in weak}, key=("old", "new").index)
        for m in METHODS:
            for label in labels:
                for p in sorted({r["ranks"] for r in weak}):
                    g = [r for r in weak if r["ranks"] == p and r["method"] == m
                         and r.get("tree", "new") == label]
                    if not g:
                        continue
                    peak = median([max(r["peak"]) for r in g])
                    base.setdefault((m, label), peak)
                    commit = sorted({r.get("commit", "") for r in g})
                    print(f"| {p} | {g[0]['n']} | {m} | {label} {', '.join(commit)} | "
                          f"{peak:.0f} | {peak / base[m, label]:.2f} | "
                          f"{median([median(r['peak']) for r in g]):.0f} | "
                          f"{median([r['seconds'] for r in g]):.0f} | {len(g)} | "
                          f"{min(r['load'] for r in g):.0f}-{max(r['load'] for r in g):.0f} |")
    census = [r for r in recs if r["kind"] == "census"]
    if census:
        diff = [r for r in census if (r["old_stable"], r["old_negative"] > 0)
                != (r["new_stable"], r["new_negative"] > 0)]
        unstable = [r for r in census if not r["old_stable"]]
        neg = [r for r in census if r["old_negative"] > 0]
        print(f"\ncensus: {len(census)} states, {len(unstable)} unstable by the exact inertia "
              f"({len(neg)} with negative curvatures), verdicts that differ: {len(diff)}; "
              f"negative counts equal in {sum(r['old_negative'] == r['new_negative'] for r in neg)}"
              f" of {len(neg)}; decided by: "
              + ", ".join(f"{m} {sum(r['new_method'] == m for r in census)}"
                          for m in ("lanczos", "inertia", "undecided")))
        for r in diff:
            print(f"  DIFF {r['state']}: old {r['old_negative']} new {r['new_negative']} "
                  f"({r['new_method']}: {r['why']})")
        steps = [r["steps"] for r in census]
        print(f"  Lanczos steps: median {median(steps):.0f}, max {max(steps)}; seconds new/old "
              f"median {median([r['seconds_new'] for r in census]):.2f} / "
              f"{median([r['seconds_old'] for r in census]):.2f}; lowest of the unstable: "
              + ", ".join(f"{r['lowest']:.2e}" for r in neg))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("states")
    a.add_argument("--dir", required=True)
    a.add_argument("--tiles", type=int, nargs="*", default=[2, 3, 4])
    a.add_argument("--phi-n", type=int, nargs="*", default=[])
    a = sub.add_parser("check")
    a.add_argument("files", nargs="+")
    a.add_argument("--ranks", type=int, nargs="+", default=[1])
    a.add_argument("--repeats", type=int, default=3)
    a.add_argument("--petsc", nargs="*", default=[], help="more PETSc options for both")
    a.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    a.add_argument("--out", required=True)
    a = sub.add_parser("weak")
    a.add_argument("--dir", required=True)
    a.add_argument("--per-rank", type=int, default=12000)
    a.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4, 8])
    a.add_argument("--repeats", type=int, default=3)
    a.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS,
                   help="the checks to run (the factorisation's memory may not fit at large P)")
    a.add_argument("--baseline", default=None,
                   help="a commit whose tree runs beside this one, interleaved (git worktree)")
    a.add_argument("--out", required=True)
    a = sub.add_parser("census")
    a.add_argument("states", nargs="+")
    a.add_argument("--out", required=True)
    a = sub.add_parser("report")
    a.add_argument("files", nargs="+")
    args = ap.parse_args()
    {"states": cmd_states, "check": cmd_check, "weak": cmd_weak, "census": cmd_census,
     "report": cmd_report}[args.cmd](args)


if __name__ == "__main__":
    main()
