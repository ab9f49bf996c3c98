"""The anomalous trial modes of Wyart et al. (2005), Eq. (rr): dR*_b = g dR_b / sqrt(e_b),
their energies against the uncut network, and the bound omega_L^2 of Eq. (kkk)."""

import numpy as np

from parjam.softmodes.linalg import allreduce, column_blocks, gram


def omega_L2(e0, kappa, z_max, grad2):
    """Eq. (kkk): omega_L^2 = e0^-1 (pi/L)^2 z_max, with (pi/L)^2 -> max|grad g|^2 for several
    planes and the stiffness factor kappa = max k r^2 (1 for harmonic contacts)."""
    return kappa * z_max * grad2 / e0


def trial_modes(V, g, e, floor=1e-12):
    """Eq. (rr): dR*_b = C_b g dR_b with C_b = e_b^-1/2 (orthonormal because G is diagonal in
    the rotated basis V); columns with e_b < floor are left at zero."""
    d = V.shape[0] // max(len(g), 1) if len(g) else 1
    C = np.where(e > floor, 1.0 / np.sqrt(np.maximum(e, floor)), 0.0)
    return np.repeat(g, d)[:, None] * V * C[None, :]


def energies(comm, M, T, projected=False, weight=None):
    """<t|M|t> per column t of T (local rows), or of weight * T without storing that product;
    with ``projected`` also T^T M T (an n x k temporary: for checks on small systems)."""
    x, y = M.createVecs()
    MT = np.empty_like(T) if projected else None
    E = np.empty(T.shape[1])
    b = 0
    for B in column_blocks(T):  # T itself, or the stored blocks of a scratch basis
        for c in range(B.shape[1]):
            t = B[:, c] if weight is None else weight * B[:, c]
            x.setArray(t)
            M.mult(x, y)
            E[b] = t @ y.getArray()
            if projected:
                MT[:, b] = y.getArray()
            b += 1
    x.destroy()
    y.destroy()
    E = allreduce(comm, E)
    if not projected:
        return E
    return E, gram(comm, T if weight is None else weight[:, None] * T, MT)
