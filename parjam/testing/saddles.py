"""Constructed saddles for the stability check's tests and benchmarks: a stable packing moved
along its softest mode (dense LAPACK: small packings only) until a contact opens, leaving a
floppy mode whose curvature the stress term of Eq. (1) makes negative, of order -p."""

import numpy as np

from parjam.net import network
from parjam.net.system import wrap
from parjam.vib import hessian


def softest_mode(pack):
    """The lowest non-translational eigenvector of the packing's dense dynamical matrix on the
    non-rattlers, as (N, d) displacements (zero on rattlers): the translations are moved far
    above the spectrum before LAPACK's eigh."""
    net = network.analyze(pack)
    c = network.active_contacts(net)
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    n, d = net.n_active, pack.d
    D = hessian.dense_hessian(n, d, c.i, c.j, blocks).reshape(n, d, n, d)
    for a in range(d):
        D[:, a, :, a] += 1e3 / n
    _, vec = np.linalg.eigh(D.reshape(n * d, -1))
    v = np.zeros((pack.n, d))
    v[~net.rattler] = vec[:, 0].reshape(-1, d)
    return net, v


def along_soft_mode(pack, opened=1):
    """A copy of ``pack`` displaced along its softest mode until ``opened`` contacts between
    particles with more than d + 1 contacts have opened (no new rattler): Nc < Nc_iso, a saddle
    (with 2, Nc = Nc_iso - 2 from an isostatic network: a floppy mode beyond the box's)."""
    net, v = softest_mode(pack)
    c = net.contacts
    deg = np.bincount(c.i, minlength=pack.n) + np.bincount(c.j, minlength=pack.n)
    rate = np.einsum("ij,ij->i", v[c.j] - v[c.i], c.rij / c.r[:, None])  # d r_ij / dt
    overlap = (1.0 - c.r / c.sigma) * c.sigma
    free = (deg[c.i] > pack.d + 1) & (deg[c.j] > pack.d + 1)
    best = None
    for sign in (1.0, -1.0):
        ok = free & (sign * rate > 0)
        t = np.sort(overlap[ok] / (sign * rate[ok]))
        k = opened - 1
        if len(t) > k and (best is None or t[k] < best[0]):
            best = (t[k], sign)
    out = pack.copy()
    out.pos = wrap(pack.pos + best[1] * best[0] * 1.0001 * v, pack.L)
    return out
