#!/usr/bin/env python3
"""Experiment (docs/scaling.md, session 8; not a parjam feature): FIRE that, when it creeps,
finds the Hessian's most negative mode and jumps downhill along it.

Runs the dphi = 1e-3 extrapolation protocol (3D mono, 1 rank) with every FIRE run cut into
chunks of K steps.  After a chunk with max|F| < 1e-5 the inertia of H + 1e-9 I (MUMPS LDL^T)
tells whether the state is a saddle; if so the most negative eigenvector comes from inverse
iteration at a shift that makes H + s I positive definite, a line search along it (downhill
sign) finds the lowest energy, and FIRE restarts from there.  Compare the FIRE steps and time
with FIRE alone (scripts/pack_steps.py) for the same N and seed.

    .venv/bin/python scripts/experiments/saddle_jumps.py N SEED K
"""

import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from parjam import env
from parjam.pack import minimize

S0 = 1e-9  # curvatures below -S0 count as negative
stats = {"checks": 0, "jumps": 0, "t_checks": 0.0}


def most_negative_mode(ff):
    """(lambda, eigenvector Vec) of the most negative eigenvalue of H, or None."""
    if not minimize.factor_shifted(ff, S0):
        return None
    s = 1e-8
    while minimize.factor_shifted(ff, s):  # a positive definite shift, by decades
        s *= 10.0
        if s > 1e-1:
            return None
    s *= 2.0
    minimize.factor_shifted(ff, s)
    ksp = ff.newton_ksp
    Hs = ksp.getOperators()[0]
    v, w = ff.vec(), ff.vec()
    v.array[:] = np.random.default_rng(0).standard_normal(v.getLocalSize())
    lam_old = None
    for _ in range(30):
        minimize.remove_translations(ff, v)
        v.scale(1.0 / v.norm())
        ksp.solve(v, w)
        w.copy(v)
        v.scale(1.0 / v.norm())
        Hs.mult(v, w)
        lam = v.dot(w) - s
        if lam_old is not None and abs(lam - lam_old) < 1e-3 * abs(lam):
            break
        lam_old = lam
    w.destroy()
    return lam, v


def jump(ff):
    """Line search downhill along the most negative mode; True if the energy fell."""
    found = most_negative_mode(ff)
    if found is None:
        return False
    lam, v = found
    f, x0 = ff.vec(), ff.vec()
    e0 = ff.evaluate(f)
    if f.dot(v) < 0:
        v.scale(-1.0)
    ff.x.copy(x0)
    best_a, best_e, a = 0.0, e0, 1e-4
    while a < 1.0:
        x0.copy(ff.x)
        ff.x.axpy(a, v)
        e = ff.evaluate(f)
        if e < best_e:
            best_a, best_e = a, e
        elif best_a > 0:
            break
        a *= 2.0
    x0.copy(ff.x)
    ff.x.axpy(best_a, v)
    ff.wrap()
    print(f"  lambda_min = {lam:.3e}, step {best_a:.3g}, dE/N = {(best_e - e0) / ff.n:.3e}",
          flush=True)
    for vec in (f, x0, v):
        vec.destroy()
    return best_a > 0


def make_fire(K):
    plain = minimize.fire

    def fire(ff, ftol, e_stop=-np.inf, params=None, progress=None, start=None, snapshot=None):
        p = params or minimize.FireParams()
        done, state = 0, start
        while True:
            last = {}

            def keep(make_state):
                last["state"] = make_state()

            cap = min(p.max_steps, (state.step if state else 0) + K)
            chunk = minimize.FireParams(**{**p.__dict__, "max_steps": cap})
            res = plain(ff, ftol, e_stop, chunk, progress, start=state, snapshot=keep)
            done = res.fire_steps
            if res.status != "not converged" or done >= p.max_steps:
                return res
            state = last.get("state")
            if res.fmax < 1e-5:
                t = time.perf_counter()
                stats["checks"] += 1
                if jump(ff):
                    stats["jumps"] += 1
                    state = minimize.FireState(np.zeros((ff.hi - ff.lo, ff.d)), p.dt, p.a0, 0,
                                                done)
                stats["t_checks"] += time.perf_counter() - t
    return fire


def main():
    n, seed, K = (int(a) for a in sys.argv[1:4])
    PETSc = env.petsc()
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    minimize.fire = make_fire(K)
    t0 = time.perf_counter()
    jam = Jammer(PETSc.COMM_SELF, random_packing(3, n, 0.70, rng=member_rng(seed, 0)))
    phi_c = jam.find_phi_c_from_above(1e-3).info["phi_c"]
    jam.ladder(phi_c, [1e-3])
    print(json.dumps({"n": n, "seed": seed, "K": K, "fire": jam.total_fire,
                      "newton": jam.total_newton, "t": time.perf_counter() - t0, **stats}))


if __name__ == "__main__":
    main()
