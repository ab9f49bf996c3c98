"""Dense LAPACK on a small system: the exact spectrum of Eq. (1) with every mode, for small N
(``parjam modes --method dense``, whole spectra of scenes) and the references of the tests.

The system is the distributed one gathered on one rank (``ActiveSystem.gathered``): the
non-rattlers numbered in ascending particle id and every contact once (i < j).  The d uniform
translations are moved above the spectrum by Hotelling deflation, so the lowest d N' - d
eigenpairs of the deflated matrix are the vibrations."""

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from parjam.net.blocks import contact_blocks
from parjam.vib.hessian import dense_hessian


@dataclass
class DenseSystem:
    """The whole non-rattler system on one rank: rows in ascending particle id ``ids``, every
    contact once (i < j in that numbering)."""

    n: int
    d: int
    ids: np.ndarray  # particle id of each row, ascending
    i: np.ndarray
    j: np.ndarray
    rij: np.ndarray
    r: np.ndarray
    sigma: np.ndarray
    alpha: float
    eps: float

    @property
    def n_modes(self):
        """Non-translational modes: d N' - d."""
        return self.d * self.n - self.d

    def blocks(self, kind):
        """Per-contact blocks K_ij of Eq. (1)."""
        return contact_blocks(self.rij, self.r, self.sigma, self.alpha, self.eps, kind)


def dense_matrix(system, kind):
    """The dense matrix of one kind (full, relaxed, stress) of a DenseSystem."""
    return dense_hessian(system.n, system.d, system.i, system.j, system.blocks(kind))


def deflated_dense(H, n, d, norm):
    """H + c T T^T with T the normalised translations and c = 2 ||H||_inf (above the spectrum):
    the translations (exact null vectors) move to c, every other eigenpair is unchanged, so the
    lowest d n - d eigenpairs are those of the deflated matrix (Hotelling deflation, O(n^2))."""
    Hs = H.copy().reshape(n, d, n, d)
    for a in range(d):
        Hs[:, a, :, a] += 2.0 * norm / n
    return Hs.reshape(n * d, n * d)


def dense_eigh(Hdefl, k=None, interval=None, vectors=True):
    """The k lowest eigenpairs of a deflated dense matrix, or those in a lambda interval."""
    kw = {"subset_by_index": [0, k - 1]} if k is not None else {"subset_by_value": interval}
    if not vectors:
        return scipy.linalg.eigh(Hdefl, eigvals_only=True, **kw), None
    return scipy.linalg.eigh(Hdefl, **kw)


def count_below_dense(Hd, sigma):
    """Eigenvalues of the symmetric Hd below sigma, from the inertia of an LDL^T factorisation
    (Sylvester): no eigen-decomposition needed."""
    _, D, _ = scipy.linalg.ldl(Hd - sigma * np.eye(len(Hd)))
    diag, off = np.diag(D).copy(), np.diag(D, 1).copy()
    return int(np.sum(scipy.linalg.eigvalsh_tridiagonal(diag, off) < 0))
