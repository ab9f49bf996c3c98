"""What the soft modes look like (Wyart et al. 2005, Sec. III and the Appendix): the sine
modulation g vanishing on the planes, the extension e = sum_i g_i^2 |dR_i|^2 of each mode, the
extended subspace (e > e0), and the overlap function f(x) with and without the trivially
localised modes.  Every function reads the basis in row chunks: no second n x n_soft array."""

import numpy as np

from parjam.softmodes.linalg import (ROW_CHUNK, allreduce, gram, replicated_eigh, rotate_rows,
                                     row_squares)

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
    w = row_weights(V, g2)
    A = np.zeros((V.shape[1], V.shape[1]))
    for a in range(0, V.shape[0], ROW_CHUNK):
        rows = V[a:a + ROW_CHUNK]
        A += rows.T @ (w[a:a + ROW_CHUNK, None] * rows)
    return allreduce(comm, A)


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
    """The trivially localised modes: for each particle left with z_i < d contacts, an
    orthonormal basis of the directions perpendicular to its remaining contact normals, as
    (particle, d-vector) pairs (same list on every rank)."""
    kept = cs.kept
    out = []
    for p in cs.localised_particles:
        mine = (kept.i == p) | (kept.j == p)
        normals = kept.rij[mine] / kept.r[mine, None]
        _, sv, Wt = np.linalg.svd(normals.reshape(-1, cs.d), full_matrices=True)
        rank = int(np.count_nonzero(sv > 1e-10))
        out += [(int(p), w) for w in Wt[rank:]]
    return out


def localised_complement(comm, cs, V, lo, hi):
    """(Q, C, W): span(V, translations) minus span(localised, translations) is spanned by the
    columns of (V - Q C) W, Q an orthonormal basis (local rows) of the localised modes and the
    translations, C = Q^T V; only small matrices besides Q (n x (#localised + d))."""
    d = cs.d
    loc = localised_vectors(cs)
    Z = np.zeros(((hi - lo) * d, len(loc) + d))
    for k, (p, w) in enumerate(loc):
        if lo <= p < hi:
            Z[(p - lo) * d:(p - lo + 1) * d, k] = w
    for a in range(d):
        Z[a::d, len(loc) + a] = 1.0 / np.sqrt(cs.n)
    R = np.linalg.cholesky(gram(comm, Z)).T
    Q = np.linalg.solve(R.T, Z.T).T  # Z R^-1: orthonormal
    C = gram(comm, Q, V)
    lam, U = replicated_eigh(comm, gram(comm, V) - C.T @ C)  # Gram matrix of V - Q C
    keep = lam > 0.5
    return Q, C, U[:, keep] / np.sqrt(lam[keep])


def without_localised(comm, cs, V, lo, hi):
    """An orthonormal basis (local rows) of the soft space with the trivially localised modes
    projected out: span(V, translations) minus span(localised, translations)."""
    Q, C, W = localised_complement(comm, cs, V, lo, hi)
    out = np.empty((V.shape[0], W.shape[1]))
    for a in range(0, V.shape[0], ROW_CHUNK):
        out[a:a + ROW_CHUNK] = (V[a:a + ROW_CHUNK] - Q[a:a + ROW_CHUNK] @ C) @ W
    return out


def overlap_without_localised(comm, cs, V, lo, hi, u, nbins):
    """f(u) of :func:`without_localised`'s basis, built one row chunk at a time."""
    Q, C, W = localised_complement(comm, cs, V, lo, hi)
    diag = np.empty(V.shape[0])
    for a in range(0, V.shape[0], ROW_CHUNK):
        rows = (V[a:a + ROW_CHUNK] - Q[a:a + ROW_CHUNK] @ C) @ W
        diag[a:a + ROW_CHUNK] = np.einsum("ij,ij->i", rows, rows)
    return overlap_from_squares(comm, diag, u, nbins, W.shape[1])
