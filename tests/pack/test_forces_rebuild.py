"""ForceField.rebuild_neighbours (the neighbour search alone, for timing it): the list it builds
is the one a force evaluation builds, and over the ranks it is the one-rank list."""

import numpy as np

from parjam import env
from parjam.pack.forces import ForceField
from parjam.pack.packing import random_packing


def test_rebuild_neighbours_is_the_evaluations_list(world):
    PETSc = env.petsc()
    pack = random_packing(3, 400, 0.7, 2.0, "bi", 1.4, np.random.default_rng(11))
    found = {}
    for name, comm in (("one", PETSc.COMM_SELF), ("world", world)):
        ff = ForceField(comm, pack.diam, pack.L, 3, pack.alpha)
        ff.set_positions(pack.pos)
        ff.rebuild_neighbours()
        pairs = np.array(ff.pairs)
        f = ff.vec()
        e = ff.evaluate(f)  # the list is fresh: the evaluation keeps it
        assert ff.n_rebuilds == 1 and np.array_equal(ff.pairs, pairs)
        ff.renew_neighbours()
        assert ff.evaluate(f) == e and ff.n_rebuilds == 2  # its own rebuild: the same list
        assert np.array_equal(ff.pairs, pairs)
        every = comm.tompi4py().allgather(pairs)  # a pair across two blocks is on both
        found[name] = np.unique(np.concatenate(every), axis=0)
        f.destroy()
        ff.destroy()
    assert len(found["one"]) > 400 and np.array_equal(found["one"], found["world"])
