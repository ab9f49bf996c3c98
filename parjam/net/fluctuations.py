"""Fluctuations of the contact number in sub-boxes of a packing.

The counting argument behind the length l* ~ 1/dz of the paper: a box of side l cut out of a
jammed packing keeps its floppy modes away only if its excess contacts, ~ dz l^d, outnumber the
contacts cut at its surface, ~ l^(d-1).  Whether the excess contact number of a box fluctuates
like a random count (variance ~ l^d) or less is measured here directly: the box is split into
m^d sub-boxes and the contacts and non-rattlers in each are counted.
"""

import numpy as np

from parjam.net.network import analyze
from parjam.net.system import wrap


def contact_fluctuations(pack, max_divisions):
    """Split the box into m^d sub-boxes of side l = L/m (m = 1..max_divisions, while l stays
    above two largest diameters), count in each the contacts among non-rattlers (by the
    contact's midpoint) and the non-rattlers, and return l, the variance of the contact count
    and the variance of the excess count dN_c = N_c - (z/2) N_box (fluctuation at fixed
    particle number), over the sub-boxes."""
    net = analyze(pack)
    c = net.contacts
    mid = wrap(pack.pos[c.i] + 0.5 * c.rij, pack.L)
    act = pack.pos[~net.rattler]
    half_z = 0.5 * net.z
    rows = []
    for m in range(1, max_divisions + 1):
        if m > 1 and pack.L / m < 2.0 * pack.diam.max():
            break

        def box_index(x):
            k = np.minimum((x / pack.L * m).astype(int), m - 1)
            return np.ravel_multi_index(k.T, (m,) * pack.d)

        nc = np.bincount(box_index(mid), minlength=m ** pack.d).astype(float)
        npart = np.bincount(box_index(act), minlength=m ** pack.d).astype(float)
        excess = nc - half_z * npart
        rows.append((pack.L / m, nc.mean(), nc.var(), excess.var(), npart.mean()))
    arr = np.array(rows)
    return {"l": arr[:, 0], "mean_contacts": arr[:, 1], "var_contacts": arr[:, 2],
            "var_excess": arr[:, 3], "mean_particles": arr[:, 4], "dz": net.dz,
            "L": pack.L}
