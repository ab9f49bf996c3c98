#!/usr/bin/env python3
"""The packing engine on the domain decomposition (parjam.pack.engine, issue 18) against the engine
it replaced (main at d5de07f: PETSc row blocks, positions gathered to every rank at each
neighbour rebuild), side by side in one run.

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_engine.py --old /work/main

Two measurements, each run as `mpirun -n P <python> scripts/bench_engine.py --worker ...` with
the old checkout's interpreter and code, then this one's:

1. ns per particle per FIRE step (3D, monodisperse, harmonic, phi = 0.70, quenched --warm steps
   first) at N = 4096 and 32768 on 1 and 2 ranks: --steps FIRE steps (parjam.pack.fire.fire) timed
   in process CPU time (the slowest rank; on a machine shared with other jobs CPU time counts
   this process's work), the fastest of --repeat in each of --rounds alternating old/new
   runs; next to the pair kernel alone
   (kernels.pair_forces on the rank's pairs touching its block, same positions).
2. Weak scaling of a FIRE quench of one member shared by P ranks, 25,000 particles per rank,
   P = 1, 2, 4, 8 (oversubscribed on this machine): --quench steps from a random start; peak
   RSS per rank (VmHWM, the largest rank's) and wall time per step.  Each rank makes only its
   own rows (a slab of the box, numbered cell by cell, as parjam.pack.packing.random_packing does),
   so that the configuration's generation does not set the peak; the diameters (N numbers) are
   the ForceField's argument in both versions.

Writes docs/bench-engine.md.
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "docs", "bench-engine.md")


def local_rows(n, L, d, lo, hi, rank, size, seed):
    """Rows [lo, hi) of a random configuration: uniform in slab ``rank`` of ``size`` along
    axis 0, numbered by cells of edge ~1.2 (neighbours get nearby ids)."""
    import numpy as np

    rng = np.random.default_rng([seed, rank])
    x = rng.uniform(0.0, 1.0, (hi - lo, d)) * L
    x[:, 0] = (rank + x[:, 0] / L) * L / size
    nc = max(1, int(L // 1.2))
    cell = np.minimum((x / L * nc).astype(np.int64), nc - 1)
    key = np.zeros(len(x), dtype=np.int64)
    for a in range(d):
        key = key * nc + cell[:, a]
    return x[np.argsort(key, kind="stable")]


def gather(ff):
    """All N positions on every rank: parjam.testing.gather in this tree, the ForceField's own
    method in the old checkout."""
    import numpy as np

    try:
        from parjam.testing.gather import gather as whole
    except ImportError:  # the old checkout
        return np.array(ff.gather())
    return whole(ff)


def field(n, phi, seed):
    import numpy as np
    from parjam import env
    from parjam.pack.forces import ForceField

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    d = 3
    L = (n * np.pi / 6.0 / phi) ** (1.0 / 3.0)
    ff = ForceField(comm, np.ones(n), L, d, 2.0)
    x = local_rows(n, L, d, ff.lo, ff.hi, comm.getRank(), comm.getSize(), seed)
    ff.x.array[:] = x.ravel()
    return ff


def worker_step(a):
    """ns / particle / step of FIRE and of the kernel alone at a.n."""
    import numpy as np
    from mpi4py import MPI
    from parjam.pack import kernels
    from parjam.pack.fire import FireParams, fire
    from parjam.net.system import neighbour_pairs_touching

    mpi = MPI.COMM_WORLD
    ff = field(a.n, 0.70, 1)
    fire(ff, 0.0, params=FireParams(max_steps=a.warm))
    start = np.array(ff.x.array_r)
    fire_ns, kern_ns = [], []
    pos = np.array(gather(ff))
    cut = 1.0 + ff.skin
    pairs = neighbour_pairs_touching(pos, ff.L, cut, ff.lo, ff.hi)
    pi, pj = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    out = np.empty((ff.hi - ff.lo, 3))
    diam = np.ones(a.n)
    del pos
    for _ in range(a.repeat):
        ff.x.array[:] = start
        mpi.Barrier()
        t = time.process_time()
        fire(ff, 0.0, params=FireParams(max_steps=a.steps))
        t = mpi.allreduce(time.process_time() - t, op=MPI.MAX)
        fire_ns.append(t / a.steps / a.n * 1e9)
        pos = np.array(gather(ff))
        mpi.Barrier()
        t = time.process_time()
        for _ in range(a.steps):
            kernels.pair_forces(pi, pj, pos, diam, ff.L, 2.0, 1.0, ff.lo, ff.hi, out)
        t = mpi.allreduce(time.process_time() - t, op=MPI.MAX)
        kern_ns.append(t / a.steps / a.n * 1e9)
        del pos
    ff.destroy()
    return {"fire": min(fire_ns), "kernel": min(kern_ns), "pairs": len(pi)}


def worker_weak(a):
    """Peak RSS per rank and wall time per step of a FIRE quench, a.per_rank particles a rank."""
    from mpi4py import MPI
    from parjam.pack.fire import FireParams, fire

    mpi = MPI.COMM_WORLD
    n = a.per_rank * mpi.Get_size()
    ff = field(n, 0.66, 2)
    mpi.Barrier()
    t = time.perf_counter()
    res = fire(ff, 0.0, params=FireParams(max_steps=a.quench))
    t = mpi.allreduce(time.perf_counter() - t, op=MPI.MAX)
    ff.destroy()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # MiB (Linux: KiB)
    rss = mpi.allgather(rss)
    return {"n": n, "step_ms": t / res.fire_steps * 1e3, "rss_max": max(rss),
            "rss_mean": sum(rss) / len(rss), "energy": res.energy}


def worker_base(a):
    """Peak RSS per rank of the same process with 64 particles a rank: libraries, MPI and PETSc
    (what no packing engine can save)."""
    from mpi4py import MPI
    from parjam.pack.fire import FireParams, fire

    mpi = MPI.COMM_WORLD
    ff = field(64 * mpi.Get_size(), 0.66, 2)
    fire(ff, 0.0, params=FireParams(max_steps=20))
    ff.destroy()
    rss = mpi.allgather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return {"rss_max": max(rss)}


def run(python, code, ranks, args):
    """One worker under mpirun; returns its JSON line."""
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    env = dict(os.environ, PYTHONPATH=code, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               OMPI_MCA_mpi_yield_when_idle="1", OMPI_MCA_rmaps_base_oversubscribe="1")
    cmd = mpirun + ["-n", str(ranks), python, os.path.abspath(__file__), "--worker",
                    "--code", code] + args
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=code)
    if res.returncode != 0:
        raise SystemExit(f"worker failed: {' '.join(cmd)}\n{res.stderr[-2000:]}")
    line = [s for s in res.stdout.splitlines() if s.startswith("{")][-1]
    return json.loads(line)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old", default="/work/main", help="checkout of the old code (its .venv)")
    p.add_argument("--n", type=int, nargs="+", default=[4096, 32768])
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--warm", type=int, default=300)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2, help="old/new alternations (fastest kept)")
    p.add_argument("--per-rank", type=int, default=25000)
    p.add_argument("--ranks", type=int, nargs="*", default=[1, 2, 4, 8],
                   help="weak-scaling rank counts; none: only the FIRE step is measured and the "
                        "weak-scaling section of the existing page is kept")
    p.add_argument("--quench", type=int, default=150)
    p.add_argument("--out", default=OUT)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--code", default=ROOT, help=argparse.SUPPRESS)
    p.add_argument("--kind", default="step", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.worker:
        sys.path.insert(0, a.code)
        from mpi4py import MPI

        a.n = a.n[0]
        out = {"step": worker_step, "weak": worker_weak, "base": worker_base}[a.kind](a)
        if MPI.COMM_WORLD.Get_rank() == 0:
            print(json.dumps(out), flush=True)
        return
    impls = {"old": (os.path.join(a.old, ".venv", "bin", "python"), a.old),
             "new": (os.path.join(ROOT, ".venv", "bin", "python"), ROOT)}
    step = {}
    for rnd in range(a.rounds):  # old, new, old, new: a load change on the machine hits both
        for n in a.n:
            for ranks in (1, 2):
                for name, (python, code) in impls.items():
                    r = run(python, code, ranks, [
                        "--kind", "step", "--n", str(n), "--steps", str(a.steps), "--warm",
                        str(a.warm), "--repeat", str(a.repeat)])
                    key = (n, ranks, name)
                    if key not in step or r["fire"] < step[key]["fire"]:
                        step[key] = r
                    print(f"round {rnd}, N = {n}, {ranks} rank(s), {name}: {r}", flush=True)
    weak = {}
    for ranks in a.ranks:
        for name, (python, code) in impls.items():
            weak[(ranks, name)] = r = run(python, code, ranks, [
                "--kind", "weak", "--per-rank", str(a.per_rank), "--quench", str(a.quench)])
            r["base"] = run(python, code, ranks, ["--kind", "base"])["rss_max"]
            print(f"weak, {ranks} rank(s), {name}: {r}", flush=True)
    write(a, step, weak)


def write(a, step, weak):
    lines = ["# Packing engine on the domain decomposition: old against new", "",
             "Written by `scripts/bench_engine.py` (one run; old = main at d5de07f with its own "
             "interpreter, new = this branch).  3D monodisperse harmonic spheres.  The machine "
             "has 2 cores shared with other jobs: CPU times per rank, oversubscribed above 2 "
             "ranks.", "",
             f"## FIRE step against the pair kernel (phi = 0.70, {a.warm} warm-up steps, "
             f"{a.steps} timed steps, fastest of {a.repeat} x {a.rounds} alternating old/new "
             "runs)", "",
             "ns per particle per step (N total; on 2 ranks the slower rank's CPU time, so "
             "ideal scaling halves it).  On 2 ranks at N = 4096 a step is ~0.5 ms of compute "
             "between collectives that wait for the other rank to be scheduled on this shared "
             "machine: both engines are latency-bound there and the ratio swings from run to "
             "run.", "",
             "| N | ranks | old FIRE step | new FIRE step | new / old | pair kernel alone |",
             "|---|---|---|---|---|---|"]
    for (n, ranks, name), r in sorted(step.items()):
        if name != "new":
            continue
        o = step[(n, ranks, "old")]
        lines.append(f"| {n} | {ranks} | {o['fire']:.0f} | {r['fire']:.0f} | "
                     f"{r['fire'] / o['fire']:.2f} | {r['kernel']:.0f} |")
    if not a.ranks:  # the step measured alone: the last weak-scaling run's section is kept
        with open(a.out) as f:
            kept = f.read()
        at = kept.find("## Weak scaling")
        if at >= 0:
            lines += ["", "(The weak-scaling section below is from an earlier run of this "
                      "script, on the engine before the one-rank periodic search.)", "",
                      kept[at:].rstrip("\n")]
        lines.append("")
        with open(a.out, "w") as f:
            f.write("\n".join(lines))
        print(f"wrote {a.out}")
        return
    base = {name: weak[(min(a.ranks), name)]["rss_max"] for name in ("old", "new")}
    lines += ["", f"## Weak scaling: one member shared by P ranks, {a.per_rank} particles per "
              f"rank (phi = 0.66, {a.quench} FIRE steps from a random start)", "",
              "Peak RSS (VmHWM) of the largest rank, and its change against P = "
              f"{min(a.ranks)}; wall time per step (oversubscribed above 2 ranks: a "
              "measure of total work, not of speed).", "",
              "The last column is the same process with 64 particles a rank (libraries, MPI, "
              "PETSc: the part of the growth no engine can save).", "",
              "| P | N | old RSS MiB | old vs P=1 | new RSS MiB | new vs P=1 | old ms/step | "
              "new ms/step | base RSS MiB (new) |", "|---|---|---|---|---|---|---|---|---|"]
    for ranks in a.ranks:
        o, r = weak[(ranks, "old")], weak[(ranks, "new")]
        lines.append(f"| {ranks} | {r['n']} | {o['rss_max']:.1f} | "
                     f"{100 * (o['rss_max'] / base['old'] - 1):+.1f} % | {r['rss_max']:.1f} | "
                     f"{100 * (r['rss_max'] / base['new'] - 1):+.1f} % | {o['step_ms']:.1f} | "
                     f"{r['step_ms']:.1f} | {r['base']:.1f} |")
    lines.append("")
    with open(a.out, "w") as f:
        f.write("\n".join(lines))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
