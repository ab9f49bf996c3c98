"""The d x d block of one contact in the dynamical matrix of Eq. (1), the paper's contact
stiffness.  For a contact ij with unit vector n = r_ij / r,

    K_ij = V''(r) n n^T  +  (V'(r)/r) (I - n n^T)
           stiffness (M)     stress / "transverse" term (M'), negative for repulsion,

and ``kind`` selects the full D = M + M', the relaxed-spring M (Section III) or the stress
term M' alone.  parjam.vib.hessian assembles the matrix from these blocks."""

import numpy as np

from parjam.net import potential

KINDS = ("full", "relaxed", "stress")


def contact_blocks(rij, r, sigma, alpha, eps=1.0, kind="full"):
    """Per-contact d x d blocks K_ij of Eq. (1) for the requested ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"unknown matrix kind {kind!r}; choose from {', '.join(KINDS)}")
    d = rij.shape[1]
    n = rij / r[:, None]
    nn = n[:, :, None] * n[:, None, :]
    blocks = np.zeros((len(r), d, d))
    if kind in ("full", "relaxed"):
        blocks += potential.d2V(r, sigma, alpha, eps)[:, None, None] * nn
    if kind in ("full", "stress"):
        t = potential.dV(r, sigma, alpha, eps) / r
        blocks += t[:, None, None] * (np.eye(d)[None] - nn)
    return blocks
