"""The d x d block of one contact in the dynamical matrix of Eq. (1), the paper's contact
stiffness.  For a contact ij with unit vector n = r_ij / r,

    K_ij = V''(r) n n^T  +  (V'(r)/r) (I - n n^T)
           stiffness (M)     stress / "transverse" term (M'), negative for repulsion,

and ``kind`` selects the full D = M + M', the relaxed-spring M (Section III) or the stress
term M' alone.  parjam.vib.hessian assembles the matrix from these blocks."""

import numpy as np

from parjam.net import potential

KINDS = ("full", "relaxed", "stress")


CHUNK = 4096  # contacts per pass: the temporaries of one pass stay in cache (~0.3 MB)


def contact_blocks(rij, r, sigma, alpha, eps=1.0, kind="full"):
    """Per-contact d x d blocks K_ij of Eq. (1) for the requested ``kind``.  Computed CHUNK
    contacts at a time, each element by the same operations as over all at once (the same
    bits), so that the memory beyond the blocks themselves is a few hundred kB, not the four
    temporaries of their size a whole-array expression makes (the peak of the stability check:
    60 MB at 200,000 contacts)."""
    if kind not in KINDS:
        raise ValueError(f"unknown matrix kind {kind!r}; choose from {', '.join(KINDS)}")
    d = rij.shape[1]
    m = len(r)
    blocks = np.empty((m, d, d))
    k = potential.d2V(r, sigma, alpha, eps) if kind in ("full", "relaxed") else None
    t = potential.dV(r, sigma, alpha, eps) / r if kind in ("full", "stress") else None
    eye = np.eye(d)[None]
    for lo in range(0, m, CHUNK):
        e = slice(lo, min(lo + CHUNK, m))
        n = rij[e] / r[e, None]
        nn = n[:, :, None] * n[:, None, :]
        b = blocks[e]
        b[...] = 0.0
        if k is not None:
            b += k[e, None, None] * nn
        if t is not None:
            b += t[e, None, None] * (eye - nn)
    return blocks
