#!/usr/bin/env python3
"""How the two ranks of one member wait for each other, step by step: each rank's work per FIRE
step (from the end of one step's reduction to its arrival at the next) and its wait at the
reduction, then how the difference of the two ranks' work is spread and how long it lasts (its
autocorrelation, and its means over blocks of 50 steps).  A difference that lasts hundreds of
steps is a core that runs slower for seconds (a shared machine), not the step-to-step noise of
two kernels.  Writes nothing; prints a table.

    source scripts/mpi-env
    $PARJAM_MPIRUN -n 2 .venv/bin/python scripts/probe_rank_jitter.py --n 65536 --warm 300 \\
        --steps 2000

The reduction is timed through a proxy of the engine's communicator (its first allreduce of a
step, FIRE's sums), so the engine runs unchanged: 3D monodisperse harmonic spheres from a random
start at phi = 0.70, as scripts/bench_pack_ranks.py.
"""

import argparse
import sys
import time

import numpy as np


class TimedComm:
    """The communicator of engine ``eng``, recording the arrival at and the return from each
    allreduce of FIRE's sums (the engine's ``sums_part``: one per step)."""

    def __init__(self, eng, log):
        self.comm, self.eng, self.log = eng.comm, eng, log

    def __getattr__(self, name):
        return getattr(self.comm, name)

    def Allreduce(self, *args, **kw):
        if len(args) > 1 and args[1] is self.eng.sums_part:
            t0 = time.perf_counter()
            out = self.comm.Allreduce(*args, **kw)
            self.log.append((t0, time.perf_counter(), self.eng.n_rebuilds))
            return out
        return self.comm.Allreduce(*args, **kw)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=65536)
    ap.add_argument("--phi", type=float, default=0.70)
    ap.add_argument("--warm", type=int, default=300, help="untimed FIRE steps first")
    ap.add_argument("--steps", type=int, default=2000, help="recorded FIRE steps")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if args.n < 64 or args.steps < 400 or args.warm < 0:
        sys.exit("probe_rank_jitter: --n >= 64, --steps >= 400 and --warm >= 0, please")

    from parjam import env

    env.init()
    PETSc = env.petsc()
    from parjam.pack.fire import FireParams, fire
    from parjam.pack.forces import ForceField
    from parjam.pack.packing import random_packing

    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    if mpi.Get_size() != 2:
        sys.exit("probe_rank_jitter: run it on 2 ranks (mpirun -n 2)")
    pack = random_packing(3, args.n, args.phi, 2.0, "mono", 1.4,
                          np.random.default_rng(args.seed))
    ff = ForceField(comm, pack.diam, pack.L, 3, 2.0)
    ff.set_positions(pack.pos)
    del pack
    fire(ff, 0.0, params=FireParams(max_steps=args.warm))
    log, start = [], ff.start_engine

    def start_timed(*a, **k):
        eng = start(*a, **k)
        eng.comm = TimedComm(eng, log)
        return eng

    ff.start_engine = start_timed
    mpi.Barrier()
    fire(ff, 0.0, params=FireParams(max_steps=args.steps))
    ff.destroy()
    t = np.array(log)
    both = mpi.gather(t, root=0)
    if mpi.Get_rank() != 0:
        return
    m = min(len(b) for b in both)
    a, b = (x[:m] for x in both)
    # one step's work, reduction to reduction, and its wait; the steps without a rebuild
    plain = np.diff(a[:, 2]) == 0
    work = [(x[1:, 0] - x[:-1, 1])[plain] for x in (a, b)]
    wait = [(x[1:, 1] - x[1:, 0])[plain] for x in (a, b)]
    rwait = [(x[1:, 1] - x[1:, 0])[~plain] for x in (a, b)]
    d = 1e3 * (work[0] - work[1])
    print(f"N = {args.n}, {m - 1} steps on 2 ranks, {int((~plain).sum())} with a rebuild; the "
          "steps without one:")
    print("| rank | work per step, ms: 10th / 50th / 90th percentile | mean | wait at the "
          "reduction, mean ms |")
    print("|---|---|---|---|")
    for r in range(2):
        q = 1e3 * np.percentile(work[r], [10, 50, 90])
        print(f"| {r} | {q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f} | {1e3 * work[r].mean():.3f} | "
              f"{1e3 * wait[r].mean():.3f} |")
    if all(len(w) for w in rwait):
        print("at the steps with a rebuild the mean wait is "
              + " and ".join(f"{1e3 * w.mean():.3f}" for w in rwait) + " ms (ranks 0 and 1)")
    c = d - d.mean()
    lags = [lag for lag in (1, 10, 50, 100, 200) if lag < len(c) // 2]
    ac = [float(np.mean(c[:-lag] * c[lag:]) / np.mean(c * c)) for lag in lags]
    print(f"\ndifference of the ranks' work (0 - 1): mean {d.mean():.3f} ms, std {d.std():.3f} ms, "
          f"correlation of the two ranks' work {np.corrcoef(work[0], work[1])[0, 1]:.2f}")
    print("autocorrelation at lags " + ", ".join(f"{lag}: {v:.2f}" for lag, v in zip(lags, ac)))
    blocks = d[: len(d) // 50 * 50].reshape(-1, 50).mean(axis=1)
    print("means over blocks of 50 steps, ms: " + " ".join(f"{v:.2f}" for v in blocks))
    big = np.abs(blocks) > 0.15 * 1e3 * np.median(np.concatenate(work))
    print(f"blocks where one rank works over 15 % longer: {int(big.sum())} of {len(blocks)}")


if __name__ == "__main__":
    main()
