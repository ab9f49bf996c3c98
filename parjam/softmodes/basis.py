"""The null-space basis of the cut system and its checks against Eq. 3 of Wyart et al. (2005):
every basis vector dR satisfies (dR_j - dR_i) . n_ij = 0 on each remaining contact."""

from dataclasses import dataclass

import numpy as np

from parjam import env
from parjam.softmodes.linalg import column_blocks

BASIS_METHODS = ("block", "krylov")
COLUMNS_DEFAULT = 64  # columns per block of the null-space method: BLAS-3 and MUMPS multi-RHS
#                       are efficient from a few tens of columns; the work arrays are n x 64
COLUMNS_MAX = 100_000  # the bound of --columns: any value above the null-space dimension is the
#                        single-block method already, so this only catches typos (a basis of
#                        1e5 columns is N d 8e5 bytes: 2.4 TB at N = 1e6 in 3D)


@dataclass
class NullBasis:
    """An orthonormal basis of the null space orthogonal to the translations.

    ``V`` holds this rank's rows (particles lo..hi-1, d rows each) of the n_soft columns (an
    array, or a :class:`parjam.softmodes.scratch.ScratchBasis` on disk);
    ``rayleigh`` the eigenvalues of M for them (round-off), ``gap`` the next eigenvalue found.
    """

    V: np.ndarray
    rayleigh: np.ndarray
    gap: float
    lo: int
    hi: int
    iterations: int
    solver: str


def eq3_residual(comm, S, V):
    """max over basis vectors and remaining contacts of |(dR_j - dR_i) . n_ij| (Eq. 3)."""
    x, y = S.createVecs()
    worst = 0.0
    for B in column_blocks(V):
        for b in range(B.shape[1]):
            x.setArray(B[:, b])
            S.mult(x, y)
            worst = max(worst, y.norm(env.petsc().NormType.INFINITY))
    x.destroy()
    y.destroy()
    return float(worst)
