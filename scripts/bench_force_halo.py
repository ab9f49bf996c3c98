#!/usr/bin/env python3
"""FIRE steps and neighbour-list rebuilds of ForceField (halo scatter per evaluation, a k-d
tree of its block and shell per rebuild) against the code they replaced (all N positions
gathered to every rank each evaluation, a k-d tree of all N on every rank per rebuild), side by
side in one run.

    source scripts/mpi-env
    $PARJAM_MPIRUN -n 2 .venv/bin/python scripts/bench_force_halo.py P.h5 --steps 1000 \
        --repeat 3 --json bench-out/force-halo.json

Both variants run ``--steps`` FIRE steps (ftol = 0, so exactly that many) from the same
perturbed positions, alternating (ABAB...) ``--repeat`` times, so that a load change on a shared
machine hits both; then ``--rebuilds`` list rebuilds each, alternating too.  Their forces
are bitwise equal (tests/net/test_potential_forces.py), hence the trajectories, neighbour-list
rebuilds and final energies are the same; the script checks that.
Rank 0 prints the milliseconds per step and per rebuild of each variant and the ratios.
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402


def rebuild_full(self, pos):
    """The rebuild before: a k-d tree of all N positions on every rank."""
    from parjam.net.system import neighbour_pairs, wrap

    pairs = neighbour_pairs(wrap(pos, self.L), self.L, self.dmax + self.skin)
    i, j = pairs[:, 0], pairs[:, 1]
    self.pairs = pairs[((i >= self.lo) & (i < self.hi)) | ((j >= self.lo) & (j < self.hi))]
    self.pairs_i = np.ascontiguousarray(self.pairs[:, 0])
    self.pairs_j = np.ascontiguousarray(self.pairs[:, 1])
    self.ref_own = np.array(pos[self.lo:self.hi])
    self.n_rebuilds += 1


def evaluate_allgather(self, f, diam):
    """The evaluation before the halo: all N positions gathered to every rank each time (and,
    as then, all N diameters on every rank)."""
    from parjam.pack import kernels
    from parjam.testing.gather import gather

    self.n_force_calls += 1
    pos = gather(self)
    self._update_pairs(pos)
    e_local = kernels.pair_forces(self.pairs_i, self.pairs_j, pos, diam, self.L,
                                  self.alpha, self.eps, self.lo, self.hi, self.local(f))
    return self.mpi.allreduce(e_local)


def force_field(comm, pack, variant):
    from parjam.pack.forces import ForceField

    ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha, pack.eps)
    if variant == "allgather":
        ff.evaluate = lambda f: evaluate_allgather(ff, f, pack.diam)
        ff._rebuild = rebuild_full.__get__(ff)
    return ff


def time_rebuilds(comm, pack, count, variant):
    from parjam.testing.gather import gather

    ff = force_field(comm, pack, variant)
    ff.set_positions(pack.pos)
    pos = np.array(gather(ff))
    comm.barrier()
    t0 = time.perf_counter()
    for _ in range(count):
        ff._rebuild(pos)
    comm.barrier()
    sec = (time.perf_counter() - t0) / count
    pairs = comm.tompi4py().allreduce(len(ff.pairs))
    ff.destroy()
    return sec, pairs


def run(comm, pack, start, steps, variant):
    from parjam.pack import minimize
    from parjam.pack.fire import fire_unfused

    ff = force_field(comm, pack, variant)
    ff.set_positions(start)
    params = minimize.FireParams(max_steps=steps)
    comm.barrier()
    t0 = time.perf_counter()
    # the FIRE that calls ff.evaluate each step (the fused step has its own kernel call)
    res = fire_unfused(ff, 0.0, params=params)
    comm.barrier()
    sec = (time.perf_counter() - t0) / steps
    out = (sec, res.energy, ff.n_rebuilds)
    ff.destroy()
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("packing")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rebuilds", type=int, default=5)
    ap.add_argument("--kick", type=float, default=1e-3,
                    help="random displacement (in diameters) applied before FIRE")
    ap.add_argument("--json", help="append the record to this JSON list (rank 0)")
    args, petsc_args = ap.parse_known_args()

    from parjam import env
    from parjam.files import h5md

    env.init(petsc_args)
    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    pack = h5md.read_packing(args.packing)
    rng = np.random.default_rng(1)
    start = pack.pos + args.kick * pack.diam.min() * rng.uniform(-1, 1, pack.pos.shape)
    times = {"allgather": [], "halo": []}
    finals = {}
    for _ in range(args.repeat):
        for variant in ("allgather", "halo"):
            sec, energy, rebuilds = run(comm, pack, start, args.steps, variant)
            times[variant].append(sec)
            finals.setdefault(variant, set()).add((energy, rebuilds))
    rebuild = {"allgather": [], "halo": []}
    pair_counts = set()
    for _ in range(args.repeat):
        for variant in ("allgather", "halo"):
            sec, pairs = time_rebuilds(comm, pack, args.rebuilds, variant)
            rebuild[variant].append(sec)
            pair_counts.add(pairs)
    same = (finals["allgather"] == finals["halo"] and len(finals["halo"]) == 1
            and len(pair_counts) == 1)
    rec = {"file": args.packing, "N": pack.n, "d": pack.d, "ranks": comm.getSize(),
           "steps": args.steps, "ms_per_step": {k: [1e3 * t for t in v] for k, v in times.items()},
           "ratio_best": min(times["allgather"]) / min(times["halo"]),
           "ms_per_rebuild": {k: [1e3 * t for t in v] for k, v in rebuild.items()},
           "rebuild_ratio_best": min(rebuild["allgather"]) / min(rebuild["halo"]),
           "same_trajectory": bool(same), "rebuilds": sorted(finals["halo"])[0][1]}
    if mpi.rank == 0:
        print(json.dumps(rec), flush=True)
        if args.json:
            old = json.load(open(args.json)) if os.path.exists(args.json) else []
            with open(args.json, "w") as fh:
                json.dump(old + [rec], fh, indent=1)
    if not same:
        sys.exit("bench_force_halo: the two variants' trajectories or pair lists differ")


if __name__ == "__main__":
    main()
