"""Dense references for the soft-mode tests (parjam.softmodes): the rigidity matrix of Eq. 3 as
a dense array, its null space by SVD, and the Appendix's peeling done literally.  For small
systems only (O(N^2) memory)."""

import numpy as np


def dense_rigidity(cs, contacts):
    """Dense S (Nc x dN') of Eq. 3 for small systems."""
    n = contacts.rij / contacts.r[:, None]
    S = np.zeros((len(contacts), cs.n, cs.d))
    rows = np.arange(len(contacts))
    S[rows, contacts.i] -= n
    S[rows, contacts.j] += n
    return S.reshape(len(contacts), cs.n * cs.d)


def dense_null_space(S, rtol=1e-8):
    """(dimension, orthonormal basis, singular values) of the null space of S by dense SVD."""
    _, s, Vt = np.linalg.svd(S, full_matrices=True)
    rank = int(np.count_nonzero(s > rtol * s[0])) if len(s) else 0
    return S.shape[1] - rank, Vt[rank:].T, s


def peel_extended(A, e0):
    """The Appendix's procedure done literally on a small dense projected G: repeatedly drop the
    direction of smallest <dR|G|dR> in the remaining space; returns q'."""
    Q = np.eye(len(A))
    while Q.shape[1]:
        a, U = np.linalg.eigh(Q.T @ A @ Q)
        if a[0] > e0:
            break
        Q = Q @ U[:, 1:]
    return Q.shape[1]
