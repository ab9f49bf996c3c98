"""Bond-orientational order: the hexatic order parameter of 2D packings, to detect the
crystallisation of monodisperse 2D systems (which then are no longer amorphous jammed solids).

psi6_j = (1/n_j) sum_k exp(6 i theta_jk) over the neighbours k of particle j (centres closer than
NEIGHBOUR_FACTOR sigma_jk: the first shell of a triangular lattice at sigma, not the second at
sqrt(3) sigma), theta_jk the angle of r_jk; the local order <|psi6_j|> averages its modulus over
particles with neighbours, the global order |<psi6_j>| the complex values (near 1 only for a
single crystal)."""

import numpy as np

from parjam.system import neighbour_pairs, pair_geometry

NEIGHBOUR_FACTOR = 1.25
CRYSTAL_THRESHOLD = 0.7  # local <|psi6|> above this: crystallised (amorphous 2D packings ~0.4..0.6)


def hexatic_order(pack):
    """(local <|psi6_j|>, global |<psi6_j>|) of a 2D packing; NaN for 3D or no neighbours."""
    if pack.d != 2:
        return float("nan"), float("nan")
    cutoff = NEIGHBOUR_FACTOR * pack.diam.max()
    pairs = neighbour_pairs(pack.pos, pack.L, cutoff)
    rij, r, sigma = pair_geometry(pack.pos, pack.L, pack.diam, pairs)
    near = r < NEIGHBOUR_FACTOR * sigma
    i, j, rij = pairs[near, 0], pairs[near, 1], rij[near]
    bond = np.exp(6j * np.arctan2(rij[:, 1], rij[:, 0]))  # exp(6i theta) is the same for -r_ij
    total = np.zeros(pack.n, complex)
    np.add.at(total, i, bond)
    np.add.at(total, j, bond)
    count = np.bincount(i, minlength=pack.n) + np.bincount(j, minlength=pack.n)
    has = count > 0
    if not has.any():
        return float("nan"), float("nan")
    psi = total[has] / count[has]
    return float(np.abs(psi).mean()), float(np.abs(psi.mean()))


def crystallised(local_order):
    return bool(np.isfinite(local_order) and local_order > CRYSTAL_THRESHOLD)
