"""A packing of soft spheres in a periodic cubic (d = 3) or square (d = 2) box, and its geometry:
diameters, volume fraction, minimum-image separations and neighbour pairs."""

from dataclasses import dataclass, field

import numpy as np

from parjam.net import potential


def sphere_volume(diam, d):
    """Volume (d = 3) or area (d = 2) of spheres of diameter ``diam``."""
    r = np.asarray(diam) / 2.0
    return np.pi * r**2 if d == 2 else 4.0 / 3.0 * np.pi * r**3


@dataclass
class Packing:
    """Positions in [0, L)^d, diameters, box edge L, and the potential's exponent alpha."""

    pos: np.ndarray
    diam: np.ndarray
    L: float
    alpha: float = 2.0
    eps: float = 1.0
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.pos = np.ascontiguousarray(self.pos, dtype=np.float64)
        self.diam = np.ascontiguousarray(self.diam, dtype=np.float64)
        self.L = float(self.L)
        self.alpha = potential.check_alpha(self.alpha)

    @property
    def n(self):
        return self.pos.shape[0]

    @property
    def d(self):
        return self.pos.shape[1]

    @property
    def volume(self):
        return self.L**self.d

    @property
    def phi(self):
        return float(sphere_volume(self.diam, self.d).sum() / self.volume)

    def box_for_phi(self, phi):
        """Box edge giving volume fraction phi with the same diameters."""
        return float((sphere_volume(self.diam, self.d).sum() / phi) ** (1.0 / self.d))

    def rescaled(self, phi):
        """Affine rescaling of the box (and positions) to volume fraction phi."""
        L = self.box_for_phi(phi)
        pos = wrap(self.pos * (L / self.L), L)
        return Packing(pos, self.diam.copy(), L, self.alpha, self.eps, dict(self.meta))

    def copy(self):
        return Packing(self.pos.copy(), self.diam.copy(), self.L, self.alpha, self.eps,
                       dict(self.meta))


def wrap(pos, L):
    """Positions folded into [0, L): floor-based, then guarded against x == L from round-off."""
    p = pos - L * np.floor(pos / L)
    p[p >= L] -= L
    p[p < 0.0] = 0.0
    return p


DUPLICATE_TOL = 1e-9  # centres closer than this times the smallest diameter coincide


def coinciding_pairs(pos, diam, L):
    """Pairs (i < j) of coinciding centres (closer than DUPLICATE_TOL x the smallest diameter):
    a packing holding one would divide by r = 0 in every force."""
    from scipy.spatial import cKDTree  # here: the data model alone loads no scipy

    pairs = cKDTree(pos, boxsize=L).query_pairs(DUPLICATE_TOL * diam.min(),
                                                output_type="ndarray")
    return np.sort(pairs, axis=1) if len(pairs) else np.zeros((0, 2), dtype=np.int64)


def min_image(dr, L):
    """Minimum-image separation vectors (positions in [0, L) keep ~1e-16 L absolute precision)."""
    return dr - L * np.rint(dr / L)


def pair_separation(xi, xj, L):
    """x_j - x_i, minimum image, keeping ~1e-16 absolute precision whatever L.

    For a pair across the boundary, x_j - x_i is ~ +-L and rounds at ulp(L) (~7e-15 for L = 40:
    a relative error of 7e-7 on an overlap of 1e-8); instead the particle near L is first moved
    down by L, which is exact (Sterbenz: x in [L/2, 2L]), and the small numbers are subtracted.
    """
    dr = xj - xi
    n = np.rint(dr / L)
    return np.where(n > 0, (xj - n * L) - xi, np.where(n < 0, xj - (xi + n * L), dr))


def neighbour_pairs(pos, L, cutoff):
    """All pairs i < j closer than ``cutoff`` (minimum image), sorted by (i, j).

    A periodic k-d tree makes this O(N log N); the box must exceed twice the cutoff so that no pair
    interacts through two images.
    """
    if L <= 2.0 * cutoff:
        raise ValueError(f"box edge {L:.3g} is not larger than twice the neighbour cutoff "
                         f"{cutoff:.3g}: too few particles for this box")
    from scipy.spatial import cKDTree

    tree = cKDTree(pos, boxsize=L)
    pairs = tree.query_pairs(cutoff, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.sort(pairs, axis=1).astype(np.int64)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def neighbour_pairs_touching(pos, L, cutoff, lo, hi):
    """``neighbour_pairs(pos, L, cutoff)`` restricted to the pairs with a particle in [lo, hi),
    in the same (i, j) order, from a k-d tree of the candidates only: the particles inside the
    periodic bounding box of [lo, hi) grown by the cutoff.  For a rank's block of cell-ordered
    particles that is its slab or block and a shell, not all N."""
    pos = wrap(np.asarray(pos, dtype=np.float64), L)
    cand = box_candidates(pos, L, cutoff, lo, hi)
    if len(cand) == len(pos):  # one rank, or a block that spans the box
        pairs = neighbour_pairs(pos, L, cutoff)
    elif len(cand) > 1:
        pairs = cand[neighbour_pairs(pos[cand], L, cutoff)]
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    return pairs[((i >= lo) & (i < hi)) | ((j >= lo) & (j < hi))]


def box_candidates(pos, L, cutoff, lo, hi):
    """Sorted indices of the particles within ``cutoff`` (per coordinate, periodically) of the
    smallest periodic box that holds particles lo..hi-1 (positions wrapped into [0, L))."""
    own = pos[lo:hi]
    if len(own) == len(pos):
        return np.arange(len(pos), dtype=np.int64)
    if len(own) == 0:
        return np.zeros(0, dtype=np.int64)
    keep = np.ones(len(pos), dtype=bool)
    cutoff = cutoff * (1.0 + 1e-9)  # a particle at the cutoff stays in despite round-off
    for k in range(pos.shape[1]):
        c = np.sort(own[:, k])
        gaps = np.diff(c, append=c[0] + L)  # the largest gap on the circle is outside the arc
        g = int(np.argmax(gaps))
        length = L - gaps[g]
        if length + 2.0 * cutoff >= L:
            continue
        start = c[(g + 1) % len(c)] - cutoff
        keep &= np.mod(pos[:, k] - start, L) <= length + 2.0 * cutoff
    return np.flatnonzero(keep).astype(np.int64)


def pair_geometry(pos, L, diam, pairs):
    """Separation vectors r_ij = x_j - x_i (minimum image), distances and sigma_ij."""
    i, j = pairs[:, 0], pairs[:, 1]
    rij = pair_separation(pos[i], pos[j], L)
    r = np.sqrt(np.einsum("ij,ij->i", rij, rij))
    sigma = 0.5 * (diam[i] + diam[j])
    return rij, r, sigma
