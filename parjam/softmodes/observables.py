"""What the soft modes look like (Wyart et al. 2005, Sec. III and the Appendix): the sine
modulation g vanishing on the planes, the extension e = sum_i g_i^2 |dR_i|^2 of each mode, the
extended subspace (e > e0), and the overlap function f(x) with and without the trivially
localised modes.  Every function reads the basis in row chunks (``V[a:z]``, an array or a
scratch basis on disk): no second n x n_soft array."""

import numpy as np

from parjam.softmodes.linalg import (ROW_CHUNK, allreduce, replicated_eigh, rotate_rows,
                                     row_squares, self_gram)

E0_LADDER = (0.05, 0.1, 0.2, 0.3, 0.4)


def planes_by_axis(planes):
    out = {}
    for p in sorted(set(planes)):
        out.setdefault(p.axis, []).append(p.frac)
    return out


def modulation(pos, L, planes):
    """g_i of Eq. (rr): the product over cut directions of sin(pi u / l), u the distance from
    the previous plane along that axis and l the spacing to the next one (one plane: l = L,
    g = sin(pi x / L) with x measured from the plane).  g vanishes on every plane."""
    g = np.ones(len(pos))
    for axis, cuts in planes_by_axis(planes).items():
        p = np.sort(cuts) * L
        u = np.mod(pos[:, axis] - p[0], L)
        starts = p - p[0]
        ends = np.append(starts[1:], L)
        k = np.searchsorted(starts, u, side="right") - 1
        g *= np.sin(np.pi * (u - starts[k]) / (ends[k] - starts[k]))
    return g


def gradient_bound(L, planes):
    """max |grad g|^2 <= sum over cut axes of (pi / l_min)^2, l_min the smallest spacing."""
    total = 0.0
    for cuts in planes_by_axis(planes).values():
        p = np.sort(cuts) * L
        spacing = np.diff(np.append(p, p[0] + L)).min()
        total += (np.pi / spacing) ** 2
    return total


def row_weights(V, g2):
    """g_i^2 on each of the d rows of particle i (V holds the local rows)."""
    d = V.shape[0] // max(len(g2), 1) if len(g2) else 1
    return np.repeat(g2, d)


def extension(comm, V, g2):
    """e_b = sum_i g_i^2 |dR_i,b|^2 of each (normalised) column; g2 per local particle."""
    w = row_weights(V, g2)
    out = np.zeros(V.shape[1])
    for a in range(0, V.shape[0], ROW_CHUNK):
        out += w[a:a + ROW_CHUNK] @ (V[a:a + ROW_CHUNK] ** 2)
    return allreduce(comm, out)


def projected_g(comm, V, g2):
    """V^T G V (G = g_i^2 on particle i), in row chunks (replicated)."""
    return self_gram(comm, V, row_weights(V, g2))


def extended_basis(comm, V, g2, inplace=False):
    """Rotate the soft basis so that G (g_i^2 on particle i) is diagonal within it.

    The Appendix removes, one at a time, the remaining mode with the smallest <dR|G|dR>: that
    is the lowest eigenvector of G projected on the remaining space, so the procedure peels off
    the eigenvectors of P G P in ascending order and q' = #{e_b > e0}.  Returns (e ascending,
    rotated local rows; ``inplace`` overwrites V instead of making a copy)."""
    e, U = replicated_eigh(comm, projected_g(comm, V, g2))  # identical on every rank
    return e, rotate_rows(V if inplace else V.copy(), U)


def extended_fraction(e, q, e0s=E0_LADDER):
    """q'/q for each e0: the number of modes of the extended subspace (e > e0) per cut."""
    return np.array([[e0, np.count_nonzero(e > e0) / q] for e0 in e0s])


def coordinate_from_plane(pos, L, plane):
    return np.mod(pos[:, plane.axis] / L - plane.frac, 1.0)


def overlap_from_squares(comm, diag, u, nbins, k):
    """f(u) from the diagonal of the soft-space projector per local row (``diag``), k modes."""
    d = len(diag) // max(len(u), 1) if len(u) else 1
    per_particle = diag.reshape(len(u), d).sum(axis=1)
    hist = np.bincount(np.minimum((u * nbins).astype(int), nbins - 1), weights=per_particle,
                       minlength=nbins)
    hist = allreduce(comm, hist)
    centres = (np.arange(nbins) + 0.5) / nbins
    return centres, hist * nbins / max(k, 1)


def overlap_function(comm, V, u, nbins):
    """f(u) on u = x/L in [0, 1) (x measured from the first plane along its axis): the trace of
    the soft-space projector per slab, sum_b sum_{i in slab} |dR_i,b|^2 / (n_modes du).

    This is the paper's q^-1 sum_b ... rescaled by L (f_paper L), normalised by the number of
    modes so that its integral is 1; it is independent of the basis chosen.
    """
    return overlap_from_squares(comm, row_squares(V), u, nbins, V.shape[1])


def localised_vectors(cs):
    """The trivially localised modes of this rank's particles: for each owned particle left
    with z_i < d contacts, an orthonormal basis of the directions perpendicular to its remaining
    contact normals, as (global active number, d-vector) pairs.  Its contacts are its own
    half-edges (sorted by owned row), so this is a search, not a loop over the contacts."""
    kept = cs.kept
    out = []
    for p in cs.localised_particles:
        a, z = np.searchsorted(kept.i, [p, p + 1])
        normals = kept.rij[a:z] / kept.r[a:z, None]
        _, sv, Wt = np.linalg.svd(normals.reshape(-1, cs.d), full_matrices=True)
        rank = int(np.count_nonzero(sv > 1e-10))
        out += [(int(p), w) for w in Wt[rank:]]
    return out


def all_localised_vectors(cs):
    """:func:`localised_vectors` of every rank, in rank order, on every rank (collective; a few
    per cut contact, never O(N))."""
    return [pw for part in cs.comm.allgather(localised_vectors(cs)) for pw in part]


def localised_complement(comm, cs, V, lo, hi):
    """(rows, C, W): span(V, translations) minus span(localised, translations) is spanned by the
    columns of (V - Q C) W, Q an orthonormal basis of the localised modes and the translations,
    C = Q^T V.  The localised modes live on single particles, so Q is never stored: ``rows(a,
    z)`` builds its local rows a..z-1 (a chunk); C, W and the Gram matrices are small."""
    d = cs.d
    loc = all_localised_vectors(cs)
    nl = len(loc)
    t = 1.0 / np.sqrt(cs.n)
    # Z = [L, T]: L orthonormal (disjoint particles, or orthonormal directions on one), T the
    # unit translations; L^T T = w_a / sqrt(n) per localised vector
    B = np.array([w * t for _, w in loc]).reshape(nl, d)
    G = np.block([[np.eye(nl), B], [B.T, np.eye(d)]])
    Rinv = np.linalg.inv(np.linalg.cholesky(G).T)  # Q = Z R^-1 is orthonormal
    ZtV = np.zeros((nl + d, V.shape[1]))
    for k, (p, w) in enumerate(loc):
        if lo <= p < hi:
            ZtV[k] = w @ V[(p - lo) * d:(p - lo + 1) * d]
    step = d * max(1, ROW_CHUNK // d)  # whole particles per chunk
    for a in range(0, V.shape[0], step):
        ZtV[nl:] += t * V[a:a + step].reshape(-1, d, V.shape[1]).sum(axis=0)
    C = Rinv.T @ allreduce(comm, ZtV)
    lam, U = replicated_eigh(comm, self_gram(comm, V) - C.T @ C)  # Gram matrix of V - Q C
    keep = lam > 0.5
    mine = [(k, p - lo, w) for k, (p, w) in enumerate(loc) if lo <= p < hi]

    def rows(a, z):
        Z = np.zeros((z - a, nl + d))
        for k, i, w in mine:  # a particle's d rows may straddle the chunk's ends
            r0, r1 = max(i * d, a), min((i + 1) * d, z)
            if r0 < r1:
                Z[r0 - a:r1 - a, k] = w[r0 - i * d:r1 - i * d]
        for c in range(d):
            Z[(np.arange(a, z) % d) == c, nl + c] = t
        return Z @ Rinv

    return rows, C, U[:, keep] / np.sqrt(lam[keep])


def without_localised(comm, cs, V, lo, hi):
    """An orthonormal basis (local rows) of the soft space with the trivially localised modes
    projected out: span(V, translations) minus span(localised, translations)."""
    rows, C, W = localised_complement(comm, cs, V, lo, hi)
    out = np.empty((V.shape[0], W.shape[1]))
    for a in range(0, V.shape[0], ROW_CHUNK):
        z = min(a + ROW_CHUNK, V.shape[0])
        out[a:z] = (V[a:z] - rows(a, z) @ C) @ W
    return out


def overlap_without_localised(comm, cs, V, lo, hi, u, nbins):
    """f(u) of :func:`without_localised`'s basis, built one row chunk at a time."""
    rows, C, W = localised_complement(comm, cs, V, lo, hi)
    diag = np.empty(V.shape[0])
    for a in range(0, V.shape[0], ROW_CHUNK):
        z = min(a + ROW_CHUNK, V.shape[0])
        P = (V[a:z] - rows(a, z) @ C) @ W
        diag[a:z] = np.einsum("ij,ij->i", P, P)
    return overlap_from_squares(comm, diag, u, nbins, W.shape[1])
