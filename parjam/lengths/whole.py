"""A large cut cube of the l* analysis (Wyart, Silbert, Nagel & Witten, PRE 72, 051306 (2005),
Section III) counted by all the ranks together, its members staying on the ranks that own them.

parjam.lengths.cubes counts one cube on one rank; a cube of an edge comparable to L would bring
that fraction of the packing there.  :func:`count_whole` makes the same count on the distributed
active network (parjam.net.active: owned non-rattlers, their half-edges, a ghost plan of the active
numbering), step by step as :func:`parjam.lengths.cubes.count_cube`:

1. members: the owned non-rattlers inside the cube; the ghosts' membership from their pulled
   positions (the same test on the same numbers).  A contact crossing a face is decided from its
   end with the smaller particle id, r_ij from that end, as the serial count's contacts are;
2. pruning of the particles with fewer than d kept contacts (``active.prune``, threshold d; the
   trivially localised modes d - z_i summed at removal);
3. connected pieces by min-label propagation (``active.components``), d(d+1)/2 rigid motions
   per piece as in ``CubeCount.rigid``;
4. the relaxed-spring matrix of the survivors, numbered by the parallel re-index
   (``active.renumber``), assembled from the half-edges directly as SBAIJ with exact
   preallocation (``hessian.assemble(rows=...)``), its null space counted by MUMPS inertia on the
   whole communicator (``cubes.null_count``, options prefix ``lengths_whole_inertia_``);
5. the extended soft modes (dense, the serial rule: cores of at most ``max_dof`` degrees of
   freedom) from the core alone, gathered on rank 0 in particle-id order and sorted there by
   ``cubes.extended_soft_count`` exactly as the serial count does (at most max_dof / d
   particles, a bounded amount whatever N), the result broadcast.

Every number of :class:`parjam.lengths.cubes.CubeCount` is a sum of this rank's share (one
allreduce each); the counts are those of the serial count of the same cube.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net.blocks import contact_blocks
from parjam import env
from parjam.net import active
from parjam.vib import hessian
from parjam.net.domain import as_mpi
from parjam.lengths.cubes import (EXTENDED_MAX_DOF, CubeCount, components, cube_members,
                                  extended_soft_count, face_cuts, null_count)
from parjam.net.network import Contacts

WHOLE_PREFIX = "lengths_whole_inertia_"  # the whole-communicator cube counts' MUMPS factorisations
PREPARE, COUNT = "parjam: l* whole-cube plan", "parjam: l* whole-cube count"
_events = {}


def event(name):
    """The PETSc log event ``name`` (PREPARE or COUNT), registered once."""
    if name not in _events:
        _events[name] = env.petsc().Log.Event(name)
    return _events[name]


@dataclass
class Ghosted:
    """The sites' half-edges on rows of [owned active rows; ghosts]: the plan every large cube
    reuses (``prepare``)."""

    halo: object  # parjam.net.domain.Halo of the active numbering (active.number_halo)
    i: np.ndarray  # owned row of each half-edge
    j: np.ndarray  # row of its other end
    pos: np.ndarray  # wrapped positions of the rows (owned, then ghosts)
    ids: np.ndarray  # particle ids of the rows
    n_own: int


def prepare(comm, sites):
    """The ghost plan of the network's other ends and their positions and ids (collective)."""
    with event(PREPARE):
        net = sites.net
        c = net.contacts
        halo = active.number_halo(comm, net.lo, net.hi, c.j)
        return Ghosted(halo, c.i - net.lo, active.halo_rows(net.lo, net.hi, halo, c.j),
                       np.concatenate([sites.pos, halo.pull(sites.pos)]),
                       np.concatenate([net.ids, halo.pull(net.ids)]), net.hi - net.lo)


def sum_int(comm, *values):
    """Integers summed over the ranks (one allreduce)."""
    return [int(v) for v in comm.allreduce(np.array(values, dtype=np.int64))]


def count_whole(comm, sites, plan, x0, ell, *, scale, e0=None, max_dof=EXTENDED_MAX_DOF):
    """Soft modes of the cube [x0, x0 + ell)^d on every rank of ``comm`` (petsc4py), its members
    where they are (module doc); the same CubeCount on every rank, equal to
    ``cubes.count_cube`` of the gathered cube."""
    with event(COUNT):
        return count(comm, sites, plan, x0, ell, scale, e0, max_dof)


def count(comm, sites, plan, x0, ell, scale, e0, max_dof):
    mpi = as_mpi(comm)
    net, d = sites.net, sites.net.d
    (n, q, nc_in), edges = kept_edges(mpi, sites, plan, x0, ell)
    alive, deficit = active.prune(mpi, plan.halo, plan.n_own, edges, d,
                                  alive=cube_members(sites.pos, sites.L, x0, ell))
    flag = np.concatenate([alive, plan.halo.pull(alive)])
    core = edges.subset(flag[edges.i] & flag[edges.j])
    del edges, flag
    trivial, n_core, nc_core = sum_int(mpi, deficit, alive.sum(), len(core.i))
    nc_core //= 2
    if n_core == 0:
        return CubeCount(ell, n, q, nc_in, 0, 0, trivial, 0, 0, d)
    _, pieces = active.components(mpi, plan.halo, plan.n_own, core, alive, net.lo)
    M = survivor_matrix(comm, plan, core, alive, net, n_core)
    try:
        null = null_count(comm, M, scale, prefix=WHOLE_PREFIX)
    finally:
        M.destroy()
    out = CubeCount(ell, n, q, nc_in, n_core, nc_core, trivial, pieces, int(null), d)
    if e0 is not None and null >= 0:
        if out.soft == 0:
            out.extended = 0
        elif d * n_core <= max_dof:
            out.extended = extended_on_root(mpi, plan, core, alive, x0, ell, net, e0)
    return out


def kept_edges(comm, sites, plan, x0, ell):
    """(n, q, Nc_in) of the cube and this rank's kept internal half-edges (rows of the plan):
    members on the owned rows and ghosts alike, each contact's face crossing decided from its
    end with the smaller particle id (module doc)."""
    g, c, L = plan, sites.net.contacts, sites.L
    member = cube_members(g.pos, L, x0, ell)
    mine = member[g.i]  # half-edges leaving an owned member
    inside = mine & member[g.j]
    k = np.flatnonzero(inside)
    canon = g.ids[g.i[k]] < g.ids[g.j[k]]  # the end the serial count takes the contact from
    start = np.where(canon[:, None], g.pos[g.i[k]], g.pos[g.j[k]])
    rij = np.where(canon[:, None], c.rij[k], -c.rij[k])
    at = np.arange(len(k))
    cut = face_cuts(start, Contacts(at, at, rij, c.r[k], c.sigma[k]), L, x0, ell)
    kept = k[~cut]
    n, leaving, n_cut, n_kept = sum_int(comm, member[:g.n_own].sum(), (mine & ~inside).sum(),
                                        cut.sum(), len(kept))
    edges = Contacts(g.i[kept], g.j[kept], c.rij[kept], c.r[kept], c.sigma[kept])
    return (n, leaving + n_cut // 2, n_kept // 2), edges


def survivor_matrix(comm, plan, core, alive, net, n_core):
    """The relaxed-spring matrix of the survivors (SBAIJ, block rows of the parallel re-index),
    from the core half-edges; its temporaries freed before the factorisation."""
    number, lo, hi = active.renumber(as_mpi(comm), plan.halo, alive)
    blocks = contact_blocks(core.rij, core.r, core.sigma, net.alpha, net.eps,
                                    "relaxed")
    return hessian.assemble(comm, n_core, net.d, number[core.i], number[core.j], blocks,
                            rows=(lo, hi), fmt="sbaij")


def extended_on_root(comm, g, core, alive, x0, ell, net, e0):
    """``cubes.extended_soft_count`` of a small core (at most EXTENDED_MAX_DOF degrees of
    freedom): its particles (positions, ids) and its contacts from their smaller-id end are
    gathered on rank 0, ordered as the serial count orders them (particle id; contacts by
    (i, j)), counted there and the count broadcast."""
    own = np.flatnonzero(alive)
    canon = g.ids[core.i] < g.ids[core.j]
    part = (g.ids[own], g.pos[own], g.ids[core.i[canon]], g.ids[core.j[canon]],
            core.rij[canon], core.r[canon], core.sigma[canon])
    parts = comm.gather(part, root=0)
    result = None
    if comm.Get_rank() == 0:
        ids, pos, ci, cj, rij, r, sigma = (np.concatenate([p[f] for p in parts])
                                           for f in range(7))
        order = np.argsort(ids)
        ids, pos = ids[order], pos[order]
        li, lj = np.searchsorted(ids, ci), np.searchsorted(ids, cj)
        o = np.lexsort((lj, li))
        li, lj, rij, r, sigma = li[o], lj[o], rij[o], r[o], sigma[o]
        n_core, d = pos.shape
        _, labels = components(n_core, li, lj, labels=True)
        blocks = contact_blocks(rij, r, sigma, net.alpha, net.eps, "relaxed")
        H = hessian.dense_hessian(n_core, d, li, lj, blocks)
        result = extended_soft_count(H, np.mod(pos - x0, net.L[0]), ell, labels, e0)
    return comm.bcast(result, root=0)
