"""One cut cube of the l* analysis (Wyart, Silbert, Nagel & Witten, PRE 72, 051306 (2005),
Section III and the Appendix): its soft modes, counted on a single-rank communicator (a cube of
more than N'/P members is counted on the whole communicator by parjam.lengths.whole, with the
same steps and these functions).

Cut every contact crossing the boundary of a cube of edge l inside the packing and keep the n
non-rattlers whose centres lie in it with their Nc_in internal contacts.  Floppy modes: at least
d n - Nc_in - d(d+1)/2 (Maxwell, rigid motions removed); every inside particle keeps its
contacts except the q cut ones, so Nc_in = (z n - q)/2 and the Maxwell count is
(q - dz n)/2 - d(d+1)/2.  :func:`count_cube` measures the actual number of non-trivial soft
modes: particles left with fewer than d contacts are removed iteratively (each removal takes
d - z_i trivially localised modes), the rigid motions d(d+1)/2 of every connected piece are
subtracted, and the null space of the relaxed-spring matrix of what remains is counted exactly
by MUMPS inertia (:func:`null_count`, options prefix ``lengths_inertia_``).  The soft modes are
also sorted by extension as in the paper's Appendix, inside the cube
(:func:`extended_soft_count`).

A cube arrives as its members only (parjam.lengths.lstar brings them to the rank that counts
it): their positions in particle-id order, the contacts among them (local indices, i < j,
r_ij = x_j - x_i) and the number of contacts that leave the cube.
"""

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from parjam.net.blocks import contact_blocks
from parjam import softmodes
from parjam.vib import hessian

EXTENDED_MAX_DOF = 2400  # dense null-space bases of cube cores up to this size
INERTIA_PREFIX = "lengths_inertia_"  # options of the cube counts' MUMPS factorisations
GAP_THRESHOLDS = (1e-10, 1e-6)  # x stiffness scale: the zero cluster and the gap above it


def cube_members(pos, L, x0, ell):
    """Mask of positions inside the periodic cube [x0, x0 + ell)^d."""
    return np.all(np.mod(pos - x0, L) < ell, axis=1)


def face_cuts(pos, contacts, L, x0, ell):
    """Mask of the contacts (both ends inside) crossing a face of the cube
    (parjam.softmodes.crossing)."""
    d = pos.shape[1]
    planes = [softmodes.Plane(a, float(np.mod(x0[a], L) / L)) for a in range(d)]
    planes += [softmodes.Plane(a, float(np.mod(x0[a] + ell, L) / L)) for a in range(d)]
    if len(contacts) == 0:
        return np.zeros(0, dtype=bool)
    return np.logical_or.reduce(softmodes.cut_masks(pos, contacts, L, planes))


def prune_underconstrained(n, d, i, j):
    """Iteratively remove particles with fewer than d contacts; returns (alive mask, number of
    trivially localised modes removed = sum of d - z_i at removal)."""
    alive = np.ones(n, dtype=bool)
    keep = np.ones(len(i), dtype=bool)
    trivial = 0
    while True:
        deg = np.bincount(i[keep], minlength=n) + np.bincount(j[keep], minlength=n)
        low = alive & (deg < d)
        if not low.any():
            return alive, trivial
        trivial += int((d - deg[low]).sum())
        alive &= ~low
        keep &= alive[i] & alive[j]


def components(n, i, j, labels=False):
    """Number of connected pieces of the contact graph (and each particle's piece)."""
    g = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    count, lab = connected_components(g, directed=False)
    return (count, lab) if labels else count


@dataclass
class CubeCount:
    ell: float
    n: int  # particles inside
    q: int  # contacts of inside particles cut by the faces
    nc_in: int  # contacts kept inside
    n_core: int  # after pruning
    nc_core: int
    trivial: int  # trivially localised modes removed by pruning
    pieces: int  # connected pieces of the core
    null: int  # null space of the core's relaxed matrix (rigid motions included; -1: no gap)
    dim: int = 3
    extended: int = -1  # soft modes with extension e > e0 (-1: not computed)

    @property
    def rigid(self):
        return self.pieces * self.dim * (self.dim + 1) // 2

    @property
    def soft(self):
        """Non-trivial soft modes: null space of the core minus the rigid motions of its
        pieces (NaN when the null space had no clear gap)."""
        return self.null - self.rigid if self.null >= 0 else float("nan")

    @property
    def maxwell_core(self):
        """d n_core - Nc_core - rigid motions: a lower bound on ``soft``."""
        return self.dim * self.n_core - self.nc_core - self.rigid

    @property
    def maxwell(self):
        """The cut-plane count of the whole cube, d n - Nc_in - d(d+1)/2 = (q - dz_in n)/2 -
        d(d+1)/2: a lower bound on all its floppy modes beyond the rigid motions."""
        return self.dim * self.n - self.nc_in - self.dim * (self.dim + 1) // 2


def rigid_motions(u, d, labels):
    """Orthonormal basis (columns, d n rows) of the translations and infinitesimal rotations of
    every connected piece (``labels``) of particles at positions u."""
    cols = []
    pairs = [(0, 1)] if d == 2 else [(0, 1), (0, 2), (1, 2)]
    for p in np.unique(labels):
        m = labels == p
        r = u - u[m].mean(axis=0)
        for a in range(d):
            v = np.zeros_like(u)
            v[m, a] = 1.0
            cols.append(v.ravel())
        for a, b in pairs:
            v = np.zeros_like(u)
            v[m, a], v[m, b] = -r[m, b], r[m, a]
            cols.append(v.ravel())
    q, _ = np.linalg.qr(np.array(cols).T)
    return q


def extended_soft_count(H, u, ell, labels, e0, zero_tol=1e-8):
    """Soft modes of a cube core that are extended (Appendix of the paper, applied inside the
    cube): the null space of the dense relaxed matrix H minus the rigid motions of its pieces,
    and the eigenvalues e of G projected on it, G multiplying particle i by
    g_i^2 = prod_a sin^2(pi u_a / ell) (u measured from the cube's corner; 2^-d for a uniform
    mode): the number of e > e0.  Surface-localised floppy clusters have e ~ 0."""
    d = u.shape[1]
    top = np.abs(H).sum(axis=1).max()
    _, V = scipy.linalg.eigh(H, subset_by_value=(-np.inf, zero_tol * top))
    R = rigid_motions(u, d, labels)
    S = V - R @ (R.T @ V)
    U, sv, _ = np.linalg.svd(S, full_matrices=False)
    soft = U[:, sv > 1e-6]
    if soft.shape[1] == 0:
        return 0
    g2 = np.repeat(np.prod(np.sin(np.pi * u / ell) ** 2, axis=1), d)
    e = np.linalg.eigvalsh(soft.T @ (g2[:, None] * soft))
    return int(np.sum(e > e0))


def count_cube(pos, internal, n_leaving, L, x0, ell, *, alpha, eps, scale, comm_self, e0=None,
               max_dof=EXTENDED_MAX_DOF):
    """Soft modes of one cube (module doc) from its members: positions ``pos`` (n, d), the
    contacts ``internal`` among them (local indices, i < j) and ``n_leaving`` contacts with one
    end outside; on a single-rank communicator.  With ``e0`` also the extended soft modes
    (dense, cores of at most ``max_dof`` degrees of freedom)."""
    n, d = pos.shape
    cut = face_cuts(pos, internal, L, x0, ell)
    kept = internal.subset(~cut)
    q = int(n_leaving + cut.sum())
    li, lj = kept.i, kept.j
    alive, trivial = prune_underconstrained(n, d, li, lj)
    core = np.cumsum(alive) - 1
    ck = alive[li] & alive[lj]
    ci, cj = core[li[ck]], core[lj[ck]]
    n_core = int(alive.sum())
    if n_core == 0:
        return CubeCount(ell, n, q, len(kept), 0, 0, trivial, 0, 0, d)
    pieces, labels = components(n_core, ci, cj, labels=True)
    blocks = contact_blocks(kept.rij[ck], kept.r[ck], kept.sigma[ck], alpha, eps,
                                    "relaxed")
    M = hessian.assemble(comm_self, n_core, d, ci, cj, blocks, fmt="sbaij")
    try:
        null = null_count(comm_self, M, scale)
    finally:
        M.destroy()
    out = CubeCount(ell, n, q, len(kept), n_core, int(ck.sum()), trivial, int(pieces),
                    int(null), d)
    if e0 is not None and null >= 0:
        if out.soft == 0:
            out.extended = 0
        elif d * n_core <= max_dof:
            u = np.mod(pos[alive] - x0, L)
            H = hessian.dense_hessian(n_core, d, ci, cj, blocks)
            out.extended = extended_soft_count(H, u, ell, labels, e0)
    return out


def null_count(comm, M, scale, prefix=INERTIA_PREFIX):
    """Null-space dimension of a cube's PSD matrix M (on one rank, or on the whole communicator
    for parjam.lengths.whole), counted by inertia (softmodes.count_below, under this command's
    own ``prefix``) at both GAP_THRESHOLDS (softmodes.gap_counts: differing counts are taken
    once more); -1 when they still differ (no clear gap: the soft count is unknown)."""
    counts = set(softmodes.gap_counts(comm, M, scale, GAP_THRESHOLDS, prefix=prefix))
    return counts.pop() if len(counts) == 1 else -1
