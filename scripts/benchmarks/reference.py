"""The peer implementations the benchmarks compare parjam with: what a numpy/scipy user would
write from a packing file, independent of parjam's own code (only its file reader is used).

- contacts and rattlers from the positions (a periodic k-d tree, rattlers removed iteratively);
- the dynamical matrix D = M + M' of the non-rattlers (paper Eq. 1: the stiffness term M and
  the stress term M'), as a scipy CSR matrix;
- the affine force fields Xi of the d^2 strains (the non-affine part of the moduli is
  Xi^T D^+ Xi / V);
- the rigidity matrix S of a contact network (its null space: the floppy modes, Eq. 3);
- a plain numpy FIRE step (the k-d tree rebuilt at every step).

Potential V(r) = (eps / alpha) (1 - r / sigma_ij)^alpha for r < sigma_ij.
"""

import time

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


class Network:
    """Contacts of the non-rattlers of a packing: particle ids ``active``, contact ends ``i``,
    ``j`` numbered among them, unit vectors ``n`` (i to j), lengths ``r``, V'' as ``k``, |V'| as
    ``f``, and the box."""

    def __init__(self, pos, diam, L, alpha=2.0, eps=1.0):
        n, d = pos.shape
        pos = np.mod(pos, L)
        pairs = cKDTree(pos, boxsize=L).query_pairs(diam.max(), output_type="ndarray")
        rij = separation(pos, pairs, L)
        sigma = 0.5 * (diam[pairs[:, 0]] + diam[pairs[:, 1]])
        touch = np.linalg.norm(rij, axis=1) < sigma
        pairs, rij, sigma = pairs[touch], rij[touch], sigma[touch]
        rattler = np.zeros(n, dtype=bool)
        while True:  # fewer than d + 1 contacts among the non-rattlers, iteratively
            live = ~rattler[pairs[:, 0]] & ~rattler[pairs[:, 1]]
            z = np.bincount(pairs[live].ravel(), minlength=n)
            new = ~rattler & (z < d + 1)
            if not new.any():
                break
            rattler |= new
        self.active = np.flatnonzero(~rattler)
        index = np.full(n, -1)
        index[self.active] = np.arange(len(self.active))
        self.pairs, rij, sigma = pairs[live], rij[live], sigma[live]
        self.i, self.j = index[self.pairs[:, 0]], index[self.pairs[:, 1]]
        self.rij = rij
        self.r = np.linalg.norm(rij, axis=1)
        self.n = rij / self.r[:, None]
        x = 1.0 - self.r / sigma
        self.k = eps * (alpha - 1.0) * x ** (alpha - 2.0) / sigma ** 2
        self.f = eps * x ** (alpha - 1.0) / sigma
        self.d, self.L, self.size = d, L, len(self.active)

    @classmethod
    def read(cls, path):
        from parjam.files import h5md

        p = h5md.read_packing(path)
        return cls(p.pos, p.diam, p.L, p.alpha, p.eps)

    def pressure(self):
        """p = (1 / (d V)) sum over contacts of |V'| r."""
        return float(np.sum(self.f * self.r) / (self.d * self.L ** self.d))

    def blocks(self, matrix="full"):
        """The d x d block of each contact: V'' n n^T (M), - |V'|/r (I - n n^T) (M')."""
        nn = self.n[:, :, None] * self.n[:, None, :]
        stress = -(self.f / self.r)[:, None, None] * (np.eye(self.d) - nn)
        if matrix == "relaxed":
            return self.k[:, None, None] * nn
        return self.k[:, None, None] * nn + stress

    def hessian(self, matrix="full", drop=None):
        """D (``matrix`` full or relaxed) of the non-rattlers, CSR; ``drop``: a boolean mask of
        contacts left out (a cut)."""
        b, i, j = self.blocks(matrix), self.i, self.j
        if drop is not None:
            b, i, j = b[~drop], i[~drop], j[~drop]
        d, a = self.d, np.arange(self.d)
        rows, cols, vals = [], [], []
        for p, q, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            rows.append(np.repeat(p[:, None] * d + a, d, axis=1).ravel())
            cols.append(np.tile(q[:, None] * d + a, (1, d)).ravel())
            vals.append((sign * b).ravel())
        m = self.size * d
        return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                      np.concatenate(cols))), shape=(m, m))

    def strain_forces(self):
        """Xi (d^2, N' d): the force each non-rattler feels when the strain e_ab is applied
        affinely (the contact block's column a times r_ij,b)."""
        b = self.blocks("full")
        out = np.zeros((self.d, self.d, self.size, self.d))
        for a in range(self.d):
            for c in range(self.d):
                g = b[:, :, a] * self.rij[:, c, None]
                np.add.at(out[a, c], self.i, g)
                np.add.at(out[a, c], self.j, -g)
        return out.reshape(self.d ** 2, -1)

    def rigidity(self, drop=None):
        """S (contacts x N' d): the change of each contact's length under displacements."""
        i, j, n = self.i, self.j, self.n
        if drop is not None:
            i, j, n = i[~drop], j[~drop], n[~drop]
        d, c = self.d, np.arange(len(i))
        rows = np.repeat(c, 2 * d)
        cols = np.concatenate([j[:, None] * d + np.arange(d), i[:, None] * d + np.arange(d)],
                              axis=1).ravel()
        vals = np.concatenate([n, -n], axis=1).ravel()
        return sp.csr_matrix((vals, (rows, cols)), shape=(len(i), self.size * d))


def separation(pos, pairs, L):
    """Minimum-image vectors from the first to the second particle of each pair."""
    rij = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    return rij - L * np.rint(rij / L)


def fire_step_seconds(pos, diam, L, steps, alpha=2.0):
    """Seconds per step of a plain numpy FIRE (the k-d tree of every particle rebuilt at every
    step, forces by np.add.at): the peer of parjam's FIRE step."""
    x, v = np.mod(pos, L), np.zeros_like(pos)
    dt, a, cut = 0.05, 0.1, diam.max()
    t0 = time.perf_counter()
    for _ in range(steps):
        pairs = cKDTree(np.mod(x, L), boxsize=L).query_pairs(cut, output_type="ndarray")
        rij = separation(x, pairs, L)
        r = np.linalg.norm(rij, axis=1)
        sigma = 0.5 * (diam[pairs[:, 0]] + diam[pairs[:, 1]])
        on = r < sigma
        fij = ((1.0 - r[on] / sigma[on]) ** (alpha - 1.0) / sigma[on] / r[on])[:, None] * rij[on]
        F = np.zeros_like(x)
        np.add.at(F, pairs[on, 1], fij)
        np.add.at(F, pairs[on, 0], -fij)
        if np.sum(F * v) > 0:
            v = (1 - a) * v + a * np.linalg.norm(v) / max(np.linalg.norm(F), 1e-300) * F
        else:
            v[:] = 0.0
        v += dt * F
        x += dt * v
    return (time.perf_counter() - t0) / steps
