"""PETSc log events around the packing engine's hot spots (parjam.logevents): -log_view shows
them, with the counts the code paths imply."""

import numpy as np

from parjam import env, logevents
from parjam.pack.fire import FireParams, fire
from parjam.pack.forces import ForceField
from parjam.pack.minimize import newton
from parjam.pack.packing import random_packing


def _counts():
    return {n: logevents.event(n).getPerfInfo()["count"] for n in logevents.NAMES}


def test_events_count_kernel_calls_rebuilds_halo_and_newton(world):
    PETSc = env.petsc()
    PETSc.Log.begin()  # what -log_view switches on
    pack = random_packing(3, 200, 0.70, 2.0, "bi", 1.4, np.random.default_rng(5))
    ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
    ff.set_positions(pack.pos)
    ff_checks, ff_plans, stop = [0], [0], ff.stop_engine

    def stop_counting():  # the engine's counts of displacement reductions and of ghost plans
        ff_checks[0] += ff.engine.n_checks
        ff_plans[0] += ff.engine.n_plans
        stop()

    ff.stop_engine = stop_counting
    before = _counts()
    res = fire(ff, 0.0, params=FireParams(max_steps=300))
    mid = _counts()
    newton(ff, 1e-12, max_steps=2)  # at least one assembly and factorisation
    after = _counts()
    ff.destroy()
    fired = {n: mid[n] - before[n] for n in logevents.NAMES}
    several = world.getSize() > 1
    steps = res.fire_steps
    assert steps == 300
    checks, plans = ff_checks[0], ff_plans[0]
    assert 0 < fired[logevents.REBUILD] < steps
    # one compiled pair search inside every rebuild, plan or not
    assert fired[logevents.SEARCH] == fired[logevents.REBUILD]
    # one kernel call per step, plus the start and the end's (the energy, which the steps did
    # not sum); two in a step where one rank rebuilt the list between the update and the
    # forces, and where several ranks reduced the largest displacement between them (at every
    # rebuild after the first, and where a bound could not tell that the list holds)
    if several:
        assert checks >= fired[logevents.REBUILD] - 1
        assert fired[logevents.FORCE] == steps + 2 + checks
    else:
        assert checks == 0
        assert steps + 2 <= fired[logevents.FORCE] <= steps + 2 + fired[logevents.REBUILD]
    # a hand-over of the slabs' particles at every rebuild that plans the ghosts anew (one rank
    # has none); the rebuilds between plans search the same rows again, without one
    if several:
        assert 1 <= plans < fired[logevents.REBUILD]
        assert fired[logevents.MIGRATE] == plans
    else:
        assert plans == fired[logevents.REBUILD] and fired[logevents.MIGRATE] == 0
    # one reduction per step, the start's and the end's, with the ghosts' forces sent before
    # it and received after it (two halo events), the checks' own, and the ghosts pulled at
    # each plan
    assert fired[logevents.ALLREDUCE] == (steps + 2 + checks if several else 0)
    assert fired[logevents.HALO] == (2 * (steps + 2) + plans if several else 0)
    assert fired[logevents.ASSEMBLY] == fired[logevents.FACTOR] == 0
    assert after[logevents.ASSEMBLY] > mid[logevents.ASSEMBLY]
    assert after[logevents.FACTOR] > mid[logevents.FACTOR]
