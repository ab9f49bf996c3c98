"""Cut-plane geometry and the cut system (Wyart et al. 2005, Sections II-III): the planes, the
bonds crossing them, and the active network (non-rattlers and their contacts) of the packing
being cut.

:func:`active_network` is the one place the non-rattlers and their contacts come from; the
distributed active network of issue 19 (item 1) replaces its body, nothing else.
"""

import re
from dataclasses import dataclass, field

import numpy as np

from parjam import network, potential
from parjam.errors import ParjamError
from parjam.network import Contacts
from parjam.softmodes.counting import expected_zero_modes

AXES = "xyz"


@dataclass(frozen=True, order=True)
class Plane:
    """The plane x_axis = frac * L."""

    axis: int
    frac: float

    @property
    def label(self):
        return f"{AXES[self.axis]}={self.frac:g}"


def parse_cut(text, d):
    """``"x=0.5"`` -> Plane(0, 0.5); the position is a fraction of the box edge in [0, 1)."""
    m = re.fullmatch(r"\s*([xyzXYZ])\s*=\s*([-+0-9.eE]+)\s*", text)
    if not m:
        raise ParjamError(f"--cut {text!r}: expected AXIS=FRACTION, e.g. x=0.5")
    axis = AXES.index(m.group(1).lower())
    try:
        frac = float(m.group(2))
    except ValueError:
        raise ParjamError(f"--cut {text!r}: {m.group(2)!r} is not a number") from None
    if axis >= d:
        raise ParjamError(f"--cut {text!r}: a {d}D packing has no {AXES[axis]} axis")
    if not (np.isfinite(frac) and 0.0 <= frac < 1.0):
        raise ParjamError(f"--cut {text!r}: the position must be a fraction of the box edge in "
                          f"[0, 1), got {frac}")
    return Plane(axis, frac)


def subdivision_planes(m, d):
    """The planes x_a = k L / m (k = 0..m-1) in every direction: the m^d sub-boxes (Sec. III)."""
    if m < 1:
        raise ParjamError(f"--subdivide must be >= 1, got {m}")
    return [Plane(a, k / m) for a in range(d) for k in range(m)]


def crossing(x_i, r_a, L, x0):
    """Mask of bonds x_i -> x_i + r_a that cross the plane x = x0 (or a periodic image of it).

    The bond crosses when its two ends lie in different periods of (x - x0) / L; |r_a| < L / 2
    (minimum image) so a bond crosses at most once.  A plane at 0 catches the bonds that wrap
    across the box edge.
    """
    return np.floor((x_i - x0) / L) != np.floor((x_i + r_a - x0) / L)


def cut_masks(pos, contacts, L, planes):
    """One mask per plane over ``contacts`` (i < j, r_ij = x_j - x_i minimum image)."""
    return [crossing(pos[contacts.i, p.axis], contacts.rij[:, p.axis], L, p.frac * L)
            for p in planes]


@dataclass
class ActiveNetwork:
    """The non-rattlers of a packing (``original``: their packing indices, ascending) and their
    contacts, in packing indices (``contacts``) and re-indexed over 0..n-1 (``local``)."""

    original: np.ndarray
    contacts: Contacts
    local: Contacts
    excess: int  # Nc - Nc_iso, Nc_iso = d(N' - 1) + 1
    n_iso: int

    @property
    def n(self):
        return len(self.original)


def active_network(pack, net=None):
    """The active network of ``pack``: rattlers removed iteratively (parjam.network.analyze, or
    ``net`` if given), the non-rattlers numbered 0..n-1 in packing order."""
    net = net if net is not None else network.analyze(pack)
    active = ~net.rattler
    index = np.cumsum(active) - 1
    c = net.contacts
    local = Contacts(index[c.i], index[c.j], c.rij, c.r, c.sigma)
    return ActiveNetwork(np.flatnonzero(active), c, local, int(net.excess), int(net.n_iso))


@dataclass
class CutSystem:
    """The non-rattlers of a packing, their contacts, and the split into kept and cut ones.

    Particle indices in ``contacts``, ``kept`` and ``cut`` run over 0..n-1 (non-rattlers of the
    uncut packing, in their original order); ``original`` maps them back to the packing.
    """

    d: int
    L: float
    alpha: float
    eps: float
    pos: np.ndarray  # (n, d) positions of the non-rattlers
    original: np.ndarray  # (n,) their indices in the packing
    contacts: Contacts  # all contacts among non-rattlers (the uncut network)
    is_cut: np.ndarray  # mask over ``contacts``
    planes: list
    excess: int  # Nc - Nc_iso of the uncut network
    n_total: int  # particles in the packing, rattlers included
    per_plane: list = field(default_factory=list)  # q of each plane (a contact may count twice)

    @property
    def n(self):
        return len(self.pos)

    @property
    def kept(self):
        return self.contacts.subset(~self.is_cut)

    @property
    def cut(self):
        return self.contacts.subset(self.is_cut)

    @property
    def q(self):
        return int(self.is_cut.sum())

    @property
    def isostatic(self):
        return self.excess == 0

    @property
    def trivial(self):
        """The d global translations."""
        return self.d

    @property
    def expected(self):
        """Null-space dimension of an isostatic packing after q cuts, d + q - 1 (Sec. II): the
        d translations plus q - 1 floppy modes (the first cut removes the single self-stress
        instead); in general :attr:`expected_general`."""
        return expected_zero_modes(self.d, self.q, 0)

    @property
    def expected_general(self):
        """d + q - 1 - (Nc - Nc_iso): the null-space dimension for any excess below q."""
        return expected_zero_modes(self.d, self.q, self.excess)

    def degree(self, kept=True):
        c = self.kept if kept else self.contacts
        return np.bincount(c.i, minlength=self.n) + np.bincount(c.j, minlength=self.n)

    @property
    def localised_particles(self):
        """Particles left with fewer than d contacts: each has d - z_i trivially localised modes
        (it moves alone, perpendicular to its remaining contacts)."""
        return np.flatnonzero(self.degree() < self.d)

    @property
    def localised(self):
        z = self.degree()
        return int(np.maximum(self.d - z, 0).sum())

    @property
    def z_max(self):
        return int(self.degree(kept=False).max())

    @property
    def kappa(self):
        """max_contacts V''(r) r^2: 1 in the paper's units (harmonic, k sigma^2 = 1, r < sigma)."""
        c = self.contacts
        return float((potential.d2V(c.r, c.sigma, self.alpha, self.eps) * c.r**2).max())

    def cut_original(self):
        """The q removed contacts as (i, j) pairs of the packing's particle indices."""
        c = self.cut
        return np.stack([self.original[c.i], self.original[c.j]], axis=1).reshape(-1, 2)


def prepare(pack, planes, allow_hyperstatic=False, net=None):
    """Remove rattlers, check isostaticity and cut the contacts crossing ``planes``."""
    if not planes:
        raise ParjamError("no cut given: use --cut AXIS=FRACTION and/or --subdivide M")
    act = active_network(pack, net)
    if act.n == 0:
        raise ParjamError(f"all {pack.n} particles are rattlers: not a jammed packing, "
                          "there is no contact network to cut")
    if act.excess != 0 and not allow_hyperstatic:
        kind = "hyperstatic" if act.excess > 0 else "hypostatic"
        raise ParjamError(
            f"the packing is not isostatic: Nc = {len(act.contacts)} contacts among N' = "
            f"{act.n} non-rattlers, Nc_iso = d(N'-1)+1 = {act.n_iso} ({kind} by "
            f"{act.excess:+d}; dphi too large?). The soft-mode count d + q - 1 needs an "
            "isostatic packing (dphi -> 0); pass --allow-hyperstatic to analyse it anyway")
    masks = cut_masks(pack.pos, act.contacts, pack.L, planes)
    for p, m in zip(planes, masks):
        if not m.any():
            raise ParjamError(f"the plane {p.label} cuts no contact among the {act.n} "
                              "non-rattlers: nothing to analyse (is the packing jammed?)")
    return CutSystem(pack.d, pack.L, pack.alpha, pack.eps, pack.pos[act.original],
                     act.original, act.local, np.logical_or.reduce(masks),
                     list(planes), act.excess, pack.n, [int(m.sum()) for m in masks])
