"""Bond-orientational order: the hexatic order parameter of 2D packings, to detect the
crystallisation of monodisperse 2D systems (which then are no longer amorphous jammed solids).

psi6_j = (1/n_j) sum_k exp(6 i theta_jk) over the neighbours k of particle j (centres closer than
NEIGHBOUR_FACTOR sigma_jk: the first shell of a triangular lattice at sigma, not the second at
sqrt(3) sigma), theta_jk the angle of r_jk; the local order <|psi6_j|> averages its modulus over
particles with neighbours, the global order |<psi6_j>| the complex values (near 1 only for a
single crystal).

Small 2D boxes order differently: 16 equal disks jam (5 of 8 seeds) in one distorted lattice
at phi_c = 0.84179, hyperstatic by +9 with z = 5, whose local hexatic order is only 0.475 (a
triangular lattice does not fit the square box).  What gives every ordered state away is the
contact count: an amorphous jammed packing is isostatic at phi_c and gains contacts only as
dz ~ z0 sqrt(dphi) above it (O'Hern et al. 2003; dz / sqrt(dphi) <= 3.7 in all 24 states of
6 bidisperse 2D members, N = 256, dphi = 1e-4 .. 1e-1, and 3.2 at N = 128, dphi = 1e-3:
docs/explanation/reliability.md), while a crystal is hyperstatic already at phi_c.  :func:`ordered_by_contacts` flags a 2D state whose excess exceeds
EXCESS_MIN contacts and whose dz exceeds DZ_FACTOR sqrt(dphi) + DZ_FINITE / N' (twice the
largest measured amorphous z0, plus a finite-size allowance of a few contacts).  It flags the
N = 16 state above and all 10 monodisperse N = 64 members at dphi = 1e-4 (hyperstatic by
7 - 22), none of the bidisperse ones.
"""

import numpy as np

from parjam.net.system import neighbour_pairs, pair_geometry

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


EXCESS_MIN = 4        # contacts above isostatic that can be a finite-size accident
DZ_FACTOR = 8.0       # > 2 x the largest amorphous dz / sqrt(dphi) measured in 2D (3.7)
DZ_FINITE = 4.0       # dz allowance 4 / N' for an isostatic state plus a few stray contacts


def amorphous_dz_limit(dphi, n_active):
    """The largest dz = z - 2d an amorphous 2D packing shows at dphi = phi - phi_c (module doc)."""
    return DZ_FACTOR * np.sqrt(max(float(dphi), 0.0)) + DZ_FINITE / max(int(n_active), 1)


def ordered_by_contacts(net, dphi):
    """Whether a 2D state at ``dphi`` (phi - phi_c; None: unknown, never flagged) is far more
    hyperstatic than an amorphous packing can be: an ordered state (module doc)."""
    if net.d != 2 or dphi is None or not np.isfinite(dphi) or net.n_active == 0:
        return False
    return bool(net.excess >= EXCESS_MIN and net.dz > amorphous_dz_limit(dphi, net.n_active))


def check(pack, net, dphi=None, hexatic=None):
    """(observables, warning or None) of a state: the hexatic order (``hexatic``: its (local,
    global) values where the caller has them, else computed from ``pack``) and the contact
    test; ``crystallised`` is 1 when either finds order (the state is not an amorphous jammed
    solid)."""
    local, glob = hexatic_order(pack) if hexatic is None else hexatic
    by_contacts = ordered_by_contacts(net, dphi)
    extra = {"hexatic_order_local": local, "hexatic_order_global": glob,
             "ordered_by_contacts": np.int8(by_contacts),
             "crystallised": np.int8(crystallised(local) or by_contacts)}
    why = []
    if crystallised(local):
        why.append(f"local hexatic order <|psi6|> = {local:.3f} > {CRYSTAL_THRESHOLD}")
    if by_contacts:
        why.append(f"hyperstatic by {net.excess:+d} contacts (dz = {net.dz:.3g} > "
                   f"{amorphous_dz_limit(dphi, net.n_active):.3g}, the most an amorphous packing "
                   f"shows at dphi = {dphi:.3g})")
    if not why:
        return extra, None
    return extra, (f"the packing crystallised ({'; '.join(why)}): not an amorphous jammed "
                   f"solid; use --dispersity bi or poly in 2D")
