"""l*, the length of the cut-plane argument (Wyart, Silbert, Nagel & Witten, PRE 72, 051306
(2005), Section III): l* ~ 1/dz, from cubes cut out of the packing at random positions.

A plane of area A is crossed by (Nc / V) <|r_a|> A contacts (r_a the component of a contact
vector along the plane normal); a cube of edge l has 2d faces of area l^(d-1) and n = rho l^d
particles, so q = 2d l^(d-1) (z rho / 2) <|r_a|> contacts are cut and soft modes appear when
q > dz n:

    l*_est = d z <|r_a|> / dz        (Maxwell estimate; <|r_a|> = <r>/2 in 3D, 2<r>/pi in 2D)

i.e. about 9 sigma / dz for monodisperse spheres in 3D and 16 <r> / (pi dz) in 2D.  The
measured l* is the edge at which the mean cut-plane count of the real cubes changes sign
(:class:`LstarResult`); since floppy clusters along the cut faces keep a few soft modes in cubes
of any size, ``lstar_extended`` is the edge above which no cube keeps an *extended* soft mode
(e > e0, default 0.4 x 2^-d, 40 % of a uniform mode; parjam.lengths.cubes).

Distribution.  The cube corners are drawn from ``seed`` identically on every rank, and the
members of every cube are counted first (one allreduce of a count per cube).  A cube of at most
N'/P members (``whole_above``) is counted on one rank, cube after cube in rounds of P: in each
round every rank finds which of its owned non-rattlers (parjam.lengths.sites) lie in each cube
of the round and sends them, and the half-edges leaving them (parjam.net.active), to the cube's rank
with one ``parjam.net.domain.send_rows`` each; the rank counts it on COMM_SELF
(parjam.lengths.cubes).  A larger cube, which would at least double its rank's share of the
packing (the default edges reach L: the whole packing), is counted by all the ranks together
with its members staying where they are (parjam.lengths.whole: distributed pruning and pieces,
the SBAIJ matrix of the survivors and MUMPS inertia on the whole communicator).  A rank so holds
its own N'/P particles plus at most N'/P members of a cube, never all N positions or all
contacts; the counts are identical to a count on one rank (members in particle-id order,
contacts in (i, j) order, each contact taken from its end with the smaller id).
"""

from dataclasses import dataclass

import numpy as np

from parjam import env
from parjam.net import potential
from parjam.net.domain import as_mpi, send_rows
from parjam.errors import ParjamError
from parjam.lengths import whole
from parjam.lengths.cubes import count_cube, cube_members
from parjam.lengths.sites import build as build_sites
from parjam.net.network import Contacts


def default_e0(d):
    """Extension threshold: 40 % of a uniform mode's 2^-d (0.1 in 2D, 0.05 in 3D)."""
    return 0.4 * 2.0 ** -d


def lstar_estimate(d, z, dz, mean_normal):
    """Maxwell estimate l* = d z <|r_a|> / dz (module doc), <|r_a|> = ``mean_normal``."""
    return d * z * mean_normal / dz if dz > 0 else float("inf")


def half_edge_means(net):
    """(<|r_a|> over contacts and axes, mean stiffness V''(r) over contacts) from this rank's
    half-edges (each contact appears twice over the ranks; one allreduce)."""
    c = net.contacts
    local = np.array([np.abs(c.rij).sum(), potential.d2V(c.r, c.sigma, net.alpha, net.eps).sum()])
    total = net.comm.allreduce(local)
    n_half = 2 * net.n_contacts
    return float(total[0] / (n_half * net.d)), float(total[1] / n_half)


def crossing_down(x, y, level):
    """The largest x (linear interpolation) below which y >= level: scanning down from the
    largest x, the first point with y >= level and its upper neighbour.  NaN if y >= level at the
    largest x (l* beyond the range) or nowhere (l* below it)."""
    hit = np.flatnonzero(np.asarray(y) >= level)
    if len(hit) == 0 or hit[-1] == len(y) - 1:
        return float("nan")
    b = hit[-1]
    t = (y[b] - level) / (y[b] - y[b + 1])
    return float(x[b] + t * (x[b + 1] - x[b]))


@dataclass
class LstarResult:
    ells: np.ndarray  # cube edges
    counts: list  # CubeCount per (edge, sample), edge-major
    samples: int
    estimate: float  # Maxwell estimate d z <|r_a|> / dz
    dz: float
    z: float
    failed: int = 0  # cubes whose null space had no clear gap (left out of the soft counts)
    e0: float = float("nan")  # extension threshold of the extended soft modes

    COLUMNS = ("edge", "mean n", "mean q", "mean cut-plane (Maxwell) count", "mean soft modes",
               "fraction with soft modes", "mean trivially localised", "cubes",
               "mean extended soft modes", "fraction with extended soft modes")

    def table(self):
        """One row per edge, the columns in COLUMNS (means over the cubes of that edge)."""
        rows = []
        for ell in self.ells:
            cs = [c for c in self.counts if c.ell == ell]
            if not cs:
                rows.append((ell,) + (np.nan,) * 6 + (0, np.nan, np.nan))
                continue
            known = [c.soft for c in cs if c.null >= 0]
            ext = np.array([c.extended for c in cs if c.extended >= 0])
            rows.append((ell, np.mean([c.n for c in cs]), np.mean([c.q for c in cs]),
                         np.mean([c.maxwell for c in cs]),
                         np.mean(known) if known else np.nan,
                         np.mean(np.array(known) > 0) if known else np.nan,
                         np.mean([c.trivial for c in cs]), len(cs),
                         ext.mean() if len(ext) else np.nan,
                         np.mean(ext > 0) if len(ext) else np.nan))
        return np.array(rows, dtype=float)

    @property
    def measured(self):
        """l*: the edge above which the mean cut-plane count of the real cubes is negative
        (fewer cut contacts than excess contacts inside)."""
        t = self.table()
        return crossing_down(t[:, 0], t[:, 3], 0.0)

    @property
    def extended_measured(self):
        """l* from the soft modes themselves: the edge above which no cube keeps an extended
        soft mode (e > e0), the geometric midpoint between the last edge where one does and the
        next; NaN if that is the largest edge (beyond the range) or there is none."""
        t = self.table()
        hit = np.flatnonzero(t[:, 9] > 0)
        if len(hit) == 0 or hit[-1] == len(t) - 1 or not np.isfinite(t[hit[-1] + 1, 9]):
            return float("nan")  # none, or the next edge was not measured (too large, no gap)
        return float(np.sqrt(t[hit[-1], 0] * t[hit[-1] + 1, 0]))

    @property
    def soft_measured(self):
        """The edge above which fewer than half of the cubes have non-trivial soft modes (NaN
        when surface-localised floppy clusters keep them at every edge)."""
        t = self.table()
        return crossing_down(t[:, 0], t[:, 5], 0.5)


def cube_corners(seed, ells, samples, d, L):
    """The corners of every cube, (edges, samples, d): the same on every rank and rank count."""
    return np.random.default_rng(seed).uniform(0.0, L, size=(len(ells), samples, d))


def local_index(num, ends):
    """Position in ``num`` (distinct numbers) of each of ``ends``, -1 where absent."""
    order = np.argsort(num)
    out = np.full(len(ends), -1, dtype=np.int64)
    if len(num) == 0:
        return out
    at = np.clip(np.searchsorted(num[order], ends), 0, len(num) - 1)
    hit = num[order][at] == ends
    out[hit] = order[at[hit]]
    return out


def gather_cube(comm, sites, x0, ell, dest):
    """Send the owned non-rattlers inside the cube [x0, x0 + ell)^d and all their half-edges
    to rank ``dest`` (collective).  Returns, on that rank, the members' positions in
    particle-id order, their internal contacts (local indices, i < j, sorted; r_ij from the end
    with the smaller id, as the serial network's) and the number of contacts leaving the cube;
    None elsewhere."""
    net, pos = sites.net, sites.pos
    rows = np.flatnonzero(cube_members(pos, sites.L, x0, ell))
    _, got = send_rows(comm, np.full(len(rows), dest), net.ids[rows],
                       {"pos": pos[rows], "num": net.lo + rows})
    c = net.contacts
    inside = np.zeros(len(pos), dtype=bool)
    inside[rows] = True
    sel = np.flatnonzero(inside[c.i - net.lo])
    _, e = send_rows(comm, np.full(len(sel), dest), c.i[sel] * np.int64(net.n_active) + c.j[sel],
                     {"i": c.i[sel], "j": c.j[sel], "rij": c.rij[sel], "r": c.r[sel],
                      "sigma": c.sigma[sel]})
    if comm.Get_rank() != dest:
        return None
    li, lj = local_index(got["num"], e["i"]), local_index(got["num"], e["j"])
    up = np.flatnonzero((lj >= 0) & (li < lj))  # internal, once
    up = up[np.lexsort((lj[up], li[up]))]
    internal = Contacts(li[up], lj[up], e["rij"][up], e["r"][up], e["sigma"][up])
    return got["pos"], internal, int(np.sum(lj < 0))


def member_counts(comm, sites, corners, ells):
    """Members (non-rattlers inside) of every cube, (edges, samples): this rank's owned ones
    summed over the ranks (one allreduce)."""
    n_e, n_s = corners.shape[:2]
    mine = np.array([[np.count_nonzero(cube_members(sites.pos, sites.L, corners[e, s], ells[e]))
                      for s in range(n_s)] for e in range(n_e)], dtype=np.int64)
    return comm.allreduce(mine)


def whole_threshold(net, size, whole_above):
    """Cubes of more members than this are counted on the whole communicator: ``whole_above``,
    by default N'/P (such a cube would at least double its rank's share of the packing)."""
    return net.n_active / size if whole_above is None else whole_above


def lstar(comm, source, ells, *, samples=8, seed=0, progress=None, e0=None, extended=True,
          whole_above=None):
    """Cut cubes of every edge in ``ells`` at ``samples`` random positions (the same on every
    rank count: positions from ``seed``) and count their soft modes (module doc): a cube of at
    most ``whole_above`` members (default N'/P) on one rank, a larger one on all the ranks
    together (parjam.lengths.whole; 0 sends every cube there, ``inf`` none).  ``source`` is a
    packing every rank holds, a rowio.Rows or a parjam.lengths.sites.Sites.  The counts are
    gathered on every rank."""
    PETSc = env.petsc()
    mpi = as_mpi(comm)
    pcomm = comm if hasattr(comm, "tompi4py") else PETSc.Comm(comm)
    sites = build_sites(mpi, source)
    net = sites.net
    if net.n_active == 0 or net.excess < 0:
        raise ParjamError(f"packing is not jammed (Nc - Nc_iso = {net.excess}): no l*")
    L = sites.L
    ells = np.asarray(sorted(float(e) for e in ells))
    if ells[0] <= 0 or ells[-1] > L:
        raise ParjamError(f"cube edges must lie in (0, L = {L:.4g}], got {list(ells)}")
    mean_normal, scale = half_edge_means(net)
    corners = cube_corners(seed, ells, samples, net.d, L)
    e0 = default_e0(net.d) if e0 is None else e0
    size = mpi.Get_size()
    members = member_counts(mpi, sites, corners, ells).ravel()
    big = members > whole_threshold(net, size, whole_above)
    alone = np.flatnonzero(~big)
    mine = []
    for first in range(0, len(alone), size):  # one round: a cube per rank, gathered, counted
        cube = None
        for dest, t in enumerate(alone[first:first + size]):
            e, s = divmod(int(t), samples)
            got = gather_cube(mpi, sites, corners[e, s], ells[e], dest)
            cube = (int(t), e, s, got) if got is not None else cube
        if cube is not None:
            t, e, s, (pos, internal, leaving) = cube
            mine.append((t, count_cube(pos, internal, leaving, L, corners[e, s], ells[e],
                                       alpha=net.alpha, eps=net.eps, scale=scale,
                                       comm_self=PETSc.COMM_SELF,
                                       e0=e0 if extended else None)))
    together = []
    if big.any():
        plan = whole.prepare(mpi, sites)
        for t in np.flatnonzero(big):
            e, s = divmod(int(t), samples)
            together.append((int(t), whole.count_whole(pcomm, sites, plan, corners[e, s],
                                                       ells[e], scale=scale,
                                                       e0=e0 if extended else None)))
    everything = sorted(sum(mpi.allgather(mine), []) + together, key=lambda x: x[0])
    failed = sum(x[1].null < 0 for x in everything)
    if progress is not None:
        progress(f"l*: {len(everything)} cubes counted ({len(together)} on all ranks "
                 f"together), {failed} without a clear gap")
    return LstarResult(ells, [x[1] for x in everything], samples,
                       lstar_estimate(net.d, net.z, net.dz, mean_normal), net.dz, net.z, failed,
                       e0 if extended else float("nan"))
