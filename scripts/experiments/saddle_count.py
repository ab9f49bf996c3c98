#!/usr/bin/env python3
"""Diagnostic (docs/scaling.md, session 8): while FIRE creeps in the dphi = 1e-3 protocol, how
many negative eigenvalues has the Hessian, and how negative are they?

Runs the extrapolation protocol (3D mono, 1 rank) and, in minimisations 3 and 4, every EVERY
FIRE steps counts the eigenvalues below -s for s in SHIFTS from the inertia of H + s I (MUMPS
LDL^T, Sylvester's law).  One JSON line per count.

    .venv/bin/python scripts/experiments/saddle_count.py N SEED EVERY
"""

import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from parjam import env
from parjam.pack import minimize

SHIFTS = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9]


def main():
    n, seed, every = (int(a) for a in sys.argv[1:4])
    PETSc = env.petsc()
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    plain_fire, plain_minimise = minimize.fire, minimize.minimize
    calls = [0]

    def fire(ff, ftol, e_stop=-np.inf, params=None, progress=None, start=None, snapshot=None):
        def count(make_state):
            if snapshot is not None:
                snapshot(make_state)
            step = make_state().step
            if calls[0] >= 3 and step % every == 0:
                f = ff.vec()
                energy = ff.evaluate(f)
                below = {str(s): minimize.factor_shifted(ff, s) for s in SHIFTS}
                print(json.dumps({"minimisation": calls[0], "step": step, "E/N": energy / ff.n,
                                  "fmax": ff.max_norm(f), "negative_below": below}), flush=True)
                f.destroy()
        return plain_fire(ff, ftol, e_stop, params, progress, start=start, snapshot=count)

    def minimise(ff, *a, **k):
        calls[0] += 1
        t = time.perf_counter()
        r = plain_minimise(ff, *a, **k)
        print(f"minimisation {calls[0]}: {r.status}, {r.fire_steps} FIRE and {r.newton_steps} "
              f"Newton steps, {time.perf_counter() - t:.1f} s", flush=True)
        return r

    minimize.fire, minimize.minimize = fire, minimise
    jam = Jammer(PETSc.COMM_SELF, random_packing(3, n, 0.70, rng=member_rng(seed, 0)))
    phi_c = jam.find_phi_c_from_above(1e-3).info["phi_c"]
    jam.ladder(phi_c, [1e-3])


if __name__ == "__main__":
    main()
