"""The d uniform translations of a periodic packing: the exact zero modes of every dynamical
matrix of Eq. (1) (sum_j K_ij (u - u) = 0 for a uniform u), removed the same way by every solver.

- ``vectors``: the d orthonormal translation Vecs in the layout of a matrix (blocks of d rows
  per particle): SLEPc's deflation space (EPSSetDeflationSpace, parjam.vib.spectrum);
- ``nullspace``: the same vectors as a PETSc MatNullSpace, for a KSP on the singular matrix and
  the near null space of its preconditioner (parjam.vib.moduli);
- ``project``: v <- v - T T^T v on a Vec in place (one allreduce of d numbers), for methods that
  only need the projector (KPM probes, parjam.vib.kpm).

One implementation for all of them; the caller destroys what it gets (``destroy``).
"""

import numpy as np

from parjam import env


def vectors(A, d):
    """The d normalised uniform translations, Vecs with the row layout of ``A``."""
    n = A.getSize()[0] // d
    out = []
    for a in range(d):
        v = A.createVecRight()
        arr = v.getArray()
        arr[:] = 0.0
        arr.reshape(-1, d)[:, a] = 1.0 / np.sqrt(n)
        out.append(v)
    return out


def nullspace(A, d):
    """(MatNullSpace of the translations, their Vecs); destroy both with ``destroy``."""
    vecs = vectors(A, d)
    ns = env.petsc().NullSpace().create(constant=False, vectors=vecs, comm=A.getComm())
    return ns, vecs


def project(v, d):
    """v <- P v, P the projector off the d translations (v a distributed Vec, blocks of d)."""
    arr = v.getArray().reshape(-1, d)
    n = v.getSize() // d
    arr -= v.getComm().tompi4py().allreduce(arr.sum(axis=0)) / n


def destroy(*objects):
    """Destroy the null space and/or lists of Vecs returned above."""
    for obj in objects:
        for o in (obj if isinstance(obj, (list, tuple)) else [obj]):
            if o is not None:
                o.destroy()
