#!/usr/bin/env python3
"""FIRE steps of one packing on 1 and 2 ranks, this tree against an older one, interleaved in one
run: the per-step time, the 2-rank speed-up and its breakdown into parjam's log events (force
kernel, halo exchange, allreduce, neighbour rebuild, the compiled pair search inside it,
migration) and the wait that load imbalance causes.  Self-contained: writes JSON, prints a table.

    source scripts/mpi-env
    nice .venv/bin/python scripts/bench_pack_ranks.py --old house --n 4096 16384 65536 \\
        --repeat 5 --json bench-out/pack-ranks.json

``--old REV`` extracts that commit of this repository (git archive) into a temporary directory
and runs it with this interpreter (its compiled kernels are built into $PARJAM_CACHE on first
use); ``--old PATH`` uses a checkout as it is.  Each measurement is a fresh process
(`mpirun -n P python bench_pack_ranks.py --worker ...`): a random start (3D, monodisperse,
harmonic, phi = 0.70 by default; --dispersity bi for the 50:50 1 : 1.4 mixture) is first
quenched for --warm FIRE steps (untimed, the same in both trees), then --steps FIRE steps are
timed between barriers (wall time, and the process CPU time of the slowest rank).  The order
of the (tree, ranks) runs is rotated from one repeat to the next, so that a change of load on a
shared machine hits all of them alike; the table gives medians over the repeats, and the load
average before and after.

``--halo-margin 1 2.2 4`` runs this tree with those ghost margins of the slab engine (in skins:
the halo's reach beyond the cutoff, which sets how many rebuilds search the same ghosts again
before a new ghost plan) side by side, as trees ``new_m1``, ``new_m2.2``, ``new_m4``;
``--balance-every 200 50`` likewise compares intervals of the engine's load balance (FIRE steps
between two comparisons of the ranks' measured work), as trees ``new_b200``, ``new_b50``.
``--co-tenant 2 1 0.4`` runs every measurement beside a job that takes 40 % of one core for 2 s,
idles 1 s, then does the same on the other core: the slowing cores of a shared machine, on purpose.

``--warm 0 --steps 1000000 --ftol 1e-13`` times a whole quench instead, from the random start
to max|F| < ftol: the per-step cost a user pays over a minimisation, early steps that rebuild the
neighbour lists every few steps and the slow relaxation that rarely does alike (FIRE takes the
same steps on any number of ranks, so the wall times compare the same work).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
EVENTS = {"kernel": "parjam: force kernel", "allreduce": "parjam: FIRE allreduce",
          "rebuild": "parjam: nbr rebuild", "halo": "parjam: halo exchange",
          "migration": "parjam: migration", "search": "parjam: nbr search"}


def worker(args):
    """One measurement on the ranks of this mpirun; rank 0 prints one JSON line."""
    import numpy as np

    from parjam import env

    env.init()
    PETSc = env.petsc()
    from parjam import logevents
    from parjam.pack import engine
    from parjam.pack.fire import FireParams, fire
    from parjam.pack.forces import ForceField
    from parjam.pack.packing import random_packing

    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    n = args.n[0]
    if args.halo_margin:
        engine.HALO_MARGIN = args.halo_margin[0]
    if args.balance_every:
        engine.BALANCE_EVERY = args.balance_every[0]
    pack = random_packing(args.dim, n, args.phi, 2.0, args.dispersity, 1.4,
                          np.random.default_rng(args.seed))
    skin = None if args.skin is None else args.skin * float(np.min(pack.diam))
    ff = ForceField(comm, pack.diam, pack.L, args.dim, 2.0, skin=skin)
    ff.set_positions(pack.pos)
    del pack
    fire(ff, 0.0, params=FireParams(max_steps=args.warm))
    if args.steady:
        return steady(args, ff, mpi, n)
    PETSc.Log.begin()
    known = {k: n for k, n in EVENTS.items() if n in logevents.NAMES}  # an older tree: fewer
    names = [known[k] for k in known]
    before = {n: logevents.event(n).getPerfInfo()["time"] for n in names}
    counts0 = {n: logevents.event(n).getPerfInfo()["count"] for n in names}
    mpi.Barrier()
    t0, c0 = time.perf_counter(), time.process_time()
    eng, stop = {}, ff.stop_engine

    def stop_counting():  # the engine's load-balance counts, before fire drops it
        eng.update(balances=ff.engine.n_balances, plans=ff.engine.n_plans)
        stop()

    ff.stop_engine = stop_counting
    res = fire(ff, args.ftol, params=FireParams(max_steps=args.steps))
    mpi.Barrier()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ev = {k: logevents.event(n).getPerfInfo()["time"] - before[n] if k in known else 0.0
          for k, n in EVENTS.items()}
    cnt = {k: logevents.event(n).getPerfInfo()["count"] - counts0[n] if k in known else 0
           for k, n in EVENTS.items()}
    per_rank = mpi.gather({"cpu": cpu, "events": ev}, root=0)
    if comm.getRank() == 0:
        steps = res.fire_steps
        kern = [r["events"]["kernel"] for r in per_rank]
        out = {"n": n, "dim": args.dim, "ranks": comm.getSize(), "steps": steps,
               "wall": wall, "ms_per_step": 1e3 * wall / steps,
               "cpu_ms_per_step": 1e3 * max(r["cpu"] for r in per_rank) / steps,
               "events_ms_per_step": {k: 1e3 * max(r["events"][k] for r in per_rank) / steps
                                      for k in EVENTS},
               "event_counts": cnt, "balances": eng.get("balances"),
               "plans": eng.get("plans"),
               "kernel_imbalance": max(kern) / (sum(kern) / len(kern)) if sum(kern) else 1.0,
               "energy": res.energy, "tree": os.path.dirname(os.path.dirname(
                   os.path.abspath(logevents.__file__)))}
        print("RESULT " + json.dumps(out), flush=True)
    ff.destroy()


def steady(args, ff, mpi, n):
    """--steady: each of --steps engine steps timed alone (a fixed dt = 0.01 and mixing, as
    FIRE's steady downhill phase), on rank 0 (the steps are synchronised by their allreduce):
    the low percentiles are the steps no other job interrupted, even on a loaded machine."""
    import numpy as np

    eng = ff.start_engine()
    s = eng.start()
    times = np.empty(args.steps)
    for k in range(args.steps):
        t = time.perf_counter()
        s = eng.step(0.01, False, 0.99, 0.01, s)
        times[k] = time.perf_counter() - t
    ff.stop_engine()
    if mpi.Get_rank() == 0:
        q = np.percentile(times, [10, 50]) * 1e3
        out = {"n": n, "dim": args.dim, "ranks": mpi.Get_size(), "steps": args.steps,
               "steady": True, "ms_per_step": float(q[0]), "p50_ms": float(q[1]),
               "min_ms": float(times.min() * 1e3), "mean_ms": float(times.mean() * 1e3),
               "cpu_ms_per_step": float("nan"), "energy": s.energy,
               "events_ms_per_step": {k: float("nan") for k in EVENTS},
               "kernel_imbalance": float("nan")}
        print("RESULT " + json.dumps(out), flush=True)
    ff.destroy()


def co_tenant(on, off, duty):
    """--co-tenant: another job sharing the machine, in turn on each core: ``on`` seconds busy
    ``duty`` of every 100 ms there, then ``off`` seconds idle (runs until killed)."""
    cores = sorted(os.sched_getaffinity(0))
    while True:
        for core in cores:
            os.sched_setaffinity(0, {core})
            end = time.time() + on
            while time.time() < end:
                t = time.time()
                while time.time() - t < duty * 0.1:
                    pass
                time.sleep((1.0 - duty) * 0.1)
            time.sleep(off)


def old_tree(rev):
    """A directory holding ``rev`` of this repository (or the path itself)."""
    if os.path.isdir(rev):
        return os.path.abspath(rev)
    dest = tempfile.mkdtemp(prefix="parjam-old-")
    archive = subprocess.run(["git", "-C", ROOT, "archive", rev], capture_output=True,
                             check=True).stdout
    subprocess.run(["tar", "-x", "-C", dest], input=archive, check=True)
    return dest


def run_one(tree, ranks, args, n, knobs):
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--n", str(n),
           "--dim", str(args.dim), "--phi", str(args.phi), "--steps", str(args.steps),
           "--warm", str(args.warm), "--seed", str(args.seed), "--ftol", repr(args.ftol),
           "--dispersity", args.dispersity]
    cmd += ["--steady"] if args.steady else []
    if args.skin is not None:
        cmd += ["--skin", str(args.skin)]
    for flag, value in knobs.items():  # this variant's engine settings
        cmd += [flag, repr(value)]
    if ranks > 1:
        cmd = mpirun + ["-n", str(ranks)] + cmd
    env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tree)
    for line in r.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"worker failed ({tree}, {ranks} ranks, N = {n}):\n{r.stderr[-2000:]}")


def median(values):
    v = sorted(values)
    m = len(v) // 2
    return v[m] if len(v) % 2 else 0.5 * (v[m - 1] + v[m])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, nargs="+", default=[4096, 16384, 65536])
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--phi", type=float, default=0.70)
    ap.add_argument("--dispersity", choices=("mono", "bi", "poly"), default="mono",
                    help="the diameters (bi: 50:50 at 1 : 1.4; poly: uniform in [1, 1.4])")
    ap.add_argument("--steps", type=int, default=1000, help="timed FIRE steps")
    ap.add_argument("--warm", type=int, default=300, help="untimed FIRE steps first")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--old", default=None, help="git revision or checkout to compare with")
    ap.add_argument("--json", default=None, help="write all runs and medians here")
    ap.add_argument("--skin", type=float, default=None,
                    help="neighbour-list skin in units of the smallest diameter (default: the "
                         "engine's, 0.2)")
    ap.add_argument("--ftol", type=float, default=0.0,
                    help="stop the timed FIRE steps when max|F| < FTOL (with --warm 0 and a "
                         "large --steps: a whole quench, the same steps on any number of ranks)")
    ap.add_argument("--halo-margin", type=float, nargs="+", default=None,
                    help="compare these ghost margins of the slab engine (in skins; "
                         "parjam.pack.engine.HALO_MARGIN, default 2.2) side by side, as trees "
                         "'new_m<M>'")
    ap.add_argument("--balance-every", type=int, nargs="+", default=None,
                    help="compare these intervals of the slab engine's load balance (FIRE steps "
                         "between comparisons of the ranks' measured work; "
                         "parjam.pack.engine.BALANCE_EVERY) side by side, as trees 'new_b<K>'")
    ap.add_argument("--co-tenant", type=float, nargs=3, default=None,
                    metavar=("ON", "OFF", "DUTY"),
                    help="run the measurements beside a job that takes DUTY of one core for ON "
                         "seconds, idles OFF seconds, then does the same on the next core (a "
                         "shared machine's slowing cores, on purpose)")
    ap.add_argument("--co-tenant-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--steady", action="store_true",
                    help="time each step alone at a fixed dt and report its 10th percentile "
                         "(the steps no other job interrupted) instead of FIRE's mean")
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return
    if args.co_tenant_worker:
        co_tenant(*args.co_tenant)
        return
    if args.co_tenant and not (args.co_tenant[0] > 0 and args.co_tenant[1] >= 0
                               and 0 < args.co_tenant[2] <= 1):
        sys.exit("bench_pack_ranks: --co-tenant takes ON > 0 and OFF >= 0 seconds, 0 < DUTY <= 1")
    if args.halo_margin and any(not 0.0 <= m < 100.0 for m in args.halo_margin):
        sys.exit("bench_pack_ranks: --halo-margin takes margins in [0, 100) skins")
    if args.balance_every and any(k < 0 for k in args.balance_every):
        sys.exit("bench_pack_ranks: --balance-every takes step counts >= 0 (0: never)")
    # label -> (tree, the engine settings of this variant: none for the tree's own)
    trees = {}
    for m in args.halo_margin or []:
        trees[f"new_m{m:g}"] = (ROOT, {"--halo-margin": m})
    for k in args.balance_every or []:
        trees[f"new_b{k}"] = (ROOT, {"--balance-every": k})
    if not trees:
        trees["new"] = (ROOT, {})
    if args.old:
        trees["old"] = (old_tree(args.old), {})
    tenant = None
    if args.co_tenant:
        tenant = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--co-tenant-worker",
                                   "--co-tenant", *map(repr, args.co_tenant)])
    try:
        runs, load = measure(args, trees)
    finally:
        if tenant is not None:
            tenant.kill()
            tenant.wait()
    report(args, trees, runs, load)


def measure(args, trees):
    """Every (tree, ranks) run of every N and repeat, rotated; the runs and the load averages."""
    runs = []
    load = [os.getloadavg()]
    configs = [(t, p) for t in trees for p in args.ranks]
    for n in args.n:
        for rep in range(args.repeat):
            k = rep % len(configs)
            for tree, p in configs[k:] + configs[:k]:
                path, knobs = trees[tree]
                r = run_one(path, p, args, n, knobs)
                r.update(tree=tree, repeat=rep, load=os.getloadavg()[0])
                runs.append(r)
                print(f"N = {n} {tree:>3} P = {p}: {r['ms_per_step']:.3f} ms/step, "
                      f"{r['steps']} steps, {r.get('event_counts', {}).get('rebuild', '-')} "
                      f"rebuilds, {r.get('plans', '-')} plans, {r.get('balances', '-')} balances "
                      f"(cpu {r['cpu_ms_per_step']:.3f}, load {r['load']:.1f})", flush=True)
    load.append(os.getloadavg())
    return runs, load


def report(args, trees, runs, load):
    """The table of medians and speed-ups, and the JSON file."""
    summary = []
    for n in args.n:
        row = {"n": n}
        for tree in trees:
            for p in args.ranks:
                sel = [r for r in runs if r["n"] == n and r["tree"] == tree and r["ranks"] == p]
                row[f"{tree}_{p}"] = median([r["ms_per_step"] for r in sel])
                row[f"{tree}_{p}_cpu"] = median([r["cpu_ms_per_step"] for r in sel])
                row[f"{tree}_{p}_events"] = {k: median([r["events_ms_per_step"][k] for r in sel])
                                             for k in EVENTS}
                row[f"{tree}_{p}_imbalance"] = median([r["kernel_imbalance"] for r in sel])
            if 1 in args.ranks and 2 in args.ranks:
                # the speed-up of each repeat (1 and 2 ranks of the same rotation), then the median
                pairs = [(a["ms_per_step"], b["ms_per_step"]) for a in runs for b in runs
                         if a["n"] == b["n"] == n and a["tree"] == b["tree"] == tree
                         and a["repeat"] == b["repeat"] and a["ranks"] == 1 and b["ranks"] == 2]
                row[f"{tree}_speedup"] = median([a / b for a, b in pairs])
        if "old" in trees and "new" in trees:  # new against old, per rank count measured
            for p in args.ranks:
                row[f"new_over_old_{p}"] = row[f"new_{p}"] / row[f"old_{p}"]
        summary.append(row)
    print(f"\nload average before {load[0][0]:.1f}, after {load[1][0]:.1f} "
          f"(1/5/15 min: {', '.join(f'{x:.1f}' for x in load[1])})")
    head = "| N | " + " | ".join(f"{t} {p} rank(s) ms/step" for t in trees for p in args.ranks)
    head += " | " + " | ".join(f"{t} speed-up" for t in trees) + " |"
    print(head)
    for row in summary:
        cells = [f"{row[f'{t}_{p}']:.3f}" for t in trees for p in args.ranks]
        cells += [f"{row.get(f'{t}_speedup', float('nan')):.2f}" for t in trees]
        print(f"| {row['n']} | " + " | ".join(cells) + " |")
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "load_before": load[0], "load_after": load[1],
                       "runs": runs, "summary": summary}, f, indent=1)


if __name__ == "__main__":
    main()
