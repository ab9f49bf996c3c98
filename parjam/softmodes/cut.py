"""Cut-plane geometry and the cut system (Wyart et al. 2005, Sections II-III): the planes, the
bonds crossing them, and the cut system on the distributed active network (parjam.net.active).

The cut system holds this rank's share only: the half-edges of the owned active rows
[lo, hi) (every contact twice over all ranks, once on the owner of each end) and each
half-edge's cut flag, computed from the owned particle's wrapped position and the separation
vector (:func:`crossing`; the reverse half-edge x_j -> x_j - r_ij crosses the same planes, so
both halves agree).  Every global number (q, localised modes, z_max, kappa, the stiffness
scale) is an allreduced sum or maximum over the owned rows, computed once when the system is
made (:func:`cut_system`), so reading it is never collective.
"""

import re
from dataclasses import dataclass, field

import numpy as np

from parjam.net import potential
from parjam.errors import ParjamError
from parjam.net.network import Contacts
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


def cut_masks(pos, contacts, L, planes, first=0):
    """One mask per plane over ``contacts`` (r_ij = x_j - x_i minimum image), each bond taken
    from its end i at ``pos[i - first]``: whole contacts (i < j) with all positions, or the
    half-edges of the owned rows first.. with the owned positions."""
    return [crossing(pos[contacts.i - first, p.axis], contacts.rij[:, p.axis], L, p.frac * L)
            for p in planes]


@dataclass
class CutSystem:
    """The cut network on this rank: the half-edges of the owned active rows [lo, hi) of the
    distributed active network ``net`` (global active numbers, i owned) and the cut flag of
    each.  Global numbers are fields, computed collectively by :func:`cut_system`."""

    net: object = field(repr=False)  # parjam.net.active.ActiveNetwork
    is_cut: np.ndarray = field(repr=False)  # mask over the half-edges ``contacts``
    planes: list
    per_plane: list  # q of each plane (a contact may count for several)
    q: int  # cut contacts among the non-rattlers (half-edge count / 2)
    localised: int  # sum_i max(d - z_i, 0) over the cut network
    z_max: int  # largest number of contacts of a particle, uncut
    kappa: float  # max_contacts V''(r) r^2 (1 in the paper's units)
    scale: float  # mean stiffness V''(r) of the kept contacts
    source: object = field(default=None, repr=False)  # the Packing the network was built
    #                                                   from (None: read by rows)

    # --- this rank's share
    @property
    def comm(self):
        return self.net.comm

    @property
    def lo(self):
        return self.net.lo

    @property
    def hi(self):
        return self.net.hi

    @property
    def n_local(self):
        return self.net.hi - self.net.lo

    @property
    def pos(self):
        """Wrapped positions of the owned active rows lo..hi-1."""
        return self.net.active_pos

    @property
    def ids(self):
        """Particle ids of the owned active rows."""
        return self.net.ids

    @property
    def contacts(self):
        """Half-edges among the non-rattlers (i owned), the uncut network."""
        return self.net.contacts

    @property
    def kept(self):
        return self.contacts.subset(~self.is_cut)

    @property
    def cut(self):
        return self.contacts.subset(self.is_cut)

    # --- global numbers (no communication)
    @property
    def d(self):
        return self.net.d

    @property
    def L(self):
        return float(self.net.L[0])

    @property
    def alpha(self):
        return self.net.alpha

    @property
    def eps(self):
        return self.net.eps

    @property
    def n(self):
        """N', the non-rattlers."""
        return self.net.n_active

    @property
    def n_total(self):
        """N, rattlers included."""
        return self.net.n

    @property
    def n_contacts(self):
        """Nc among the non-rattlers, uncut."""
        return self.net.n_contacts

    @property
    def excess(self):
        """Nc - Nc_iso of the uncut network."""
        return int(self.net.excess)

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
        """Contacts z_i of each owned active row (its half-edges: every contact of an owned
        particle is stored on this rank)."""
        c = self.kept if kept else self.contacts
        return np.bincount(c.i - self.lo, minlength=self.n_local)

    @property
    def localised_particles(self):
        """Owned particles (global active numbers) left with fewer than d contacts: each has
        d - z_i trivially localised modes (it moves alone, perpendicular to its remaining
        contacts)."""
        return self.lo + np.flatnonzero(self.degree() < self.d)

    def gathered(self):
        """The whole cut network on every rank (collective; small systems only: tests, figures
        and dense references): :class:`WholeCut`, rows in the global active numbering."""
        mpi = self.comm
        up = self.contacts.i < self.contacts.j  # each contact once
        c = self.contacts.subset(up)
        parts = mpi.allgather((self.pos, self.ids, c.i, c.j, c.rij, c.r, c.sigma,
                               self.is_cut[up], self.localised_particles))
        cat = [np.concatenate(col) for col in zip(*parts)]
        contacts = Contacts(*cat[2:7])
        order = np.lexsort((contacts.j, contacts.i))
        return WholeCut(self.d, self.L, cat[0], cat[1], contacts.subset(order), cat[7][order],
                        cat[8])


@dataclass
class WholeCut:
    """A cut system gathered on one rank (:meth:`CutSystem.gathered`): contacts i < j, once."""

    d: int
    L: float
    pos: np.ndarray  # (N', d)
    original: np.ndarray  # particle id of each active number
    contacts: Contacts
    is_cut: np.ndarray
    localised_particles: np.ndarray

    @property
    def n(self):
        return len(self.pos)

    @property
    def kept(self):
        return self.contacts.subset(~self.is_cut)

    @property
    def cut(self):
        return self.contacts.subset(self.is_cut)


def half_edge_masks(net, planes):
    """One mask per plane over the half-edges of ``net``, each from its owned end."""
    return cut_masks(net.active_pos, net.contacts, float(net.L[0]), planes, first=net.lo)


def cut_system(net, planes, is_cut, per_plane, source=None):
    """The :class:`CutSystem` of the half-edge mask ``is_cut`` (collective: q, the localised
    count, z_max, kappa and the stiffness scale are allreduced here, once)."""
    from mpi4py import MPI

    mpi = net.comm
    c = net.contacts
    kept = c.subset(~is_cut)
    d = net.d
    z = np.bincount(kept.i - net.lo, minlength=net.hi - net.lo)
    z_all = np.bincount(c.i - net.lo, minlength=net.hi - net.lo)
    k = potential.d2V(c.r, c.sigma, net.alpha, net.eps)
    sums = mpi.allreduce(np.array([is_cut.sum(), np.maximum(d - z, 0).sum(),
                                   k[~is_cut].sum(), len(kept)], dtype=float))
    n_cut = int(round(sums[0]))
    if n_cut % 2:
        raise ParjamError("the two ends of a cut contact disagree on which side of a plane it "
                          "lies (a particle on the plane to round-off?); move the plane")
    z_max = mpi.allreduce(int(z_all.max()) if len(z_all) else 0, op=MPI.MAX)
    kappa = mpi.allreduce(float((k * c.r**2).max()) if len(c) else 0.0, op=MPI.MAX)
    return CutSystem(net, is_cut, list(planes), [int(p) for p in per_plane], n_cut // 2,
                     int(round(sums[1])), z_max, kappa,
                     float(sums[2] / sums[3]) if sums[3] else 1.0, source)


def prepare(pack, planes, allow_hyperstatic=False, net=None, comm=None):
    """The cut system: the distributed active network (``net``, from parjam.net.active.from_rows, or
    built from the packing ``pack`` every rank holds on ``comm``, default COMM_SELF), checked
    for isostaticity, its half-edges crossing ``planes`` cut (collective)."""
    if not planes:
        raise ParjamError("no cut given: use --cut AXIS=FRACTION and/or --subdivide M")
    if net is None:
        from parjam import env
        from parjam.net import active

        comm = comm if comm is not None else env.petsc().COMM_SELF
        net = active.from_packing(comm, pack)
    if net.n_active == 0:
        raise ParjamError(f"all {net.n} particles are rattlers: not a jammed packing, "
                          "there is no contact network to cut")
    if net.excess != 0 and not allow_hyperstatic:
        kind = "hyperstatic" if net.excess > 0 else "hypostatic"
        raise ParjamError(
            f"the packing is not isostatic: Nc = {net.n_contacts} contacts among N' = "
            f"{net.n_active} non-rattlers, Nc_iso = d(N'-1)+1 = {net.n_iso} ({kind} by "
            f"{net.excess:+d}; dphi too large?). The soft-mode count d + q - 1 needs an "
            "isostatic packing (dphi -> 0); pass --allow-hyperstatic to analyse it anyway")
    masks = half_edge_masks(net, planes)
    per_plane = net.comm.allreduce(np.array([m.sum() for m in masks], dtype=np.int64)) // 2
    for p, q in zip(planes, per_plane):
        if q == 0:
            raise ParjamError(f"the plane {p.label} cuts no contact among the "
                              f"{net.n_active} non-rattlers: nothing to analyse (is the "
                              "packing jammed?)")
    return cut_system(net, planes, np.logical_or.reduce(masks), per_plane, source=pack)


def bound_to(cs, comm):
    """``cs`` on the communicator ``comm``: itself when its network lives there, else (a system
    prepared from a packing on another communicator) the same cut made again on ``comm``."""
    from mpi4py import MPI

    mine = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    if MPI.Comm.Compare(mine, cs.comm) in (MPI.IDENT, MPI.CONGRUENT):
        return cs
    if cs.source is None:
        raise ParjamError("a cut system read by rows cannot move to another communicator")
    from parjam.net import active

    net = active.from_packing(comm, cs.source)
    masks = half_edge_masks(net, cs.planes)
    return cut_system(net, cs.planes, np.logical_or.reduce(masks), cs.per_plane, cs.source)
