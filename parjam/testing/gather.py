"""Whole-configuration copies of a force field's distributed values (parjam.pack.forces.ForceField),
for tests and benchmark scripts only.  The packing path of parjam proper holds no array of
length N on any rank: its files and checkpoints go by rows, so these gathers live
here, outside it.  Each call builds its scatter to all ranks and frees it before returning (no
(N, d) buffer stays with the force field)."""

import numpy as np

from parjam import env


def gather(ff, vec=None):
    """All N rows (N, d) of ``ff``'s positions, or of ``vec`` (a Vec of the positions' layout,
    e.g. forces), as a new array on every rank (collective).  While FIRE runs on the engine,
    the positions are fetched from it first."""
    PETSc = env.petsc()
    if vec is None and ff.engine is not None:
        ff.sync_engine()
    scatter, whole = PETSc.Scatter.toAll(ff.x)
    try:
        scatter.scatter(ff.x if vec is None else vec, whole, PETSc.InsertMode.INSERT,
                        PETSc.ScatterMode.FORWARD)
        return np.array(whole.array_r).reshape(ff.n, ff.d)
    finally:
        scatter.destroy()
        whole.destroy()


def gather_engine(ff, values):
    """All N rows of per-particle ``values`` of the engine's rows (e.g. its velocities or
    forces, (n_rows, d)) as a new (N, d) array on every rank (collective)."""
    tmp = ff.vec()
    try:
        tmp.array[:] = ff.block_rows(values).ravel()
        return gather(ff, tmp)
    finally:
        tmp.destroy()
