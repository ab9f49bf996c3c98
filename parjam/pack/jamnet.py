"""The packing protocol's per-state contact network on the slabs of parjam.net.domain:
what the Jammer asks of every minimised state (energy, pressure, residual forces, mean contact
force and stiffness, N', Nc - Nc_iso) from the positions each rank holds, with O(N/P) memory.

It is parjam.net.active's construction (``SlabDomain.balanced`` + ``migrate`` to the slabs, one
ghost exchange, ``half_edges``, iterative ``remove_rattlers``, the parallel ``renumber``), with
the per-contact and per-particle numbers taken the way the serial ``network.analyze`` takes
them:

- every contact is summed once, on the owner of its lower-id end (the half-edges with
  id_i < id_j), in (id_i, id_j) order: the serial contact order.  The separation of such a
  half-edge is the serial one (``system.pair_separation`` of the wrapped positions, i -> j);
- the force on a particle is its contacts with lower-id partners (ascending) minus those with
  higher-id partners (ascending): ``network.particle_forces``' two bincounts, in their order.

The sums over contacts (energy, stress, the mean contact force and stiffness) are exact
(parjam.net.exactsum: one allreduce of integer accumulators, rounded once), so every number is
the same bits on any number of ranks (the serial ``network.analyze``'s numpy sums agree with
them to round-off); counts, rattlers and the maximum force are exact.  ``ActiveEdges`` keeps
the half-edges among the non-rattlers (active numbers, this rank's rows [lo, hi)) for the
distributed Hessian of parjam.pack.stability, ordered so that its assembly on one rank is
the serial one.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net import exactsum, potential
from parjam.net.active import half_edges, max_op, remove_rattlers, renumber, row_block
from parjam.net.domain import SlabDomain, as_mpi
from parjam.net.network import NetworkNumbers


@dataclass
class SlabState:
    """One state's particles on the slabs: this rank's rows (wrapped positions, global ids,
    diameters), sorted by id, and the decomposition."""

    comm: object  # mpi4py
    dom: SlabDomain
    L: float
    x: np.ndarray
    ids: np.ndarray
    diam: np.ndarray
    cutoff: float  # contact search: max diameter (1 + 1e-9), as network.find_contacts


def slab_state(comm, x, diam, ids, L):
    """The rows any rank holds (``x``, ``diam``, global ``ids``) handed to the slabs of a
    balanced decomposition (collective)."""
    comm = as_mpi(comm)
    x = np.asarray(x, dtype=np.float64)
    dom = SlabDomain.balanced(comm, L, x)
    x, ids, f = dom.migrate(x, ids, {"diam": np.asarray(diam, dtype=np.float64)})
    dmax = comm.allreduce(float(f["diam"].max()) if len(ids) else 0.0, op=max_op())
    return SlabState(comm, dom, float(L), x, ids, f["diam"], dmax * (1.0 + 1e-9))


def contact_edges(state, x=None):
    """Half-edges of every contact at positions ``x`` (default the state's; the rows stay with
    their owners) as (Contacts in rows of [owned; ghosts], halo, global ids of those rows,
    mask of the half-edges that carry their contact once: id_i < id_j)."""
    x = state.x if x is None else x
    edges, halo, gid = half_edges(state.dom, x, state.diam, state.ids, state.cutoff)
    return edges, halo, gid, state.ids[edges.i] < gid[edges.j]


@dataclass
class ActiveEdges:
    """The half-edges among non-rattlers in active numbers, owned rows [lo, hi): first the
    contacts whose owned end is the lower (by (i, j)), then those whose owned end is the higher
    (by (j, i)): hessian.half_edges_of's order, so one rank assembles the serial matrix.  ``rij``
    points from the owned end."""

    n: int  # N'
    lo: int
    hi: int
    n_up: int  # the first n_up half-edges have the lower-id end owned
    i: np.ndarray
    j: np.ndarray
    rij: np.ndarray
    r: np.ndarray
    sigma: np.ndarray
    ids: np.ndarray  # global ids of the owned active rows lo..hi-1


@dataclass
class JamNetwork(NetworkNumbers):
    """The numbers of network.Network the Jammer uses, for a state on the slabs."""

    d: int
    n: int
    n_active: int
    n_contacts: int
    phi: float
    alpha: float
    eps: float
    energy: float
    stress: np.ndarray
    max_force: float
    mean_force: float
    mean_stiffness: float  # mean V''(r) over the contacts among non-rattlers (0: none)
    state: SlabState
    rattler: np.ndarray  # owned rows
    active: ActiveEdges

    @property
    def pressure(self):
        return float(np.trace(self.stress) / self.d)

    @property
    def n_rattlers(self):
        return self.n - self.n_active


def build(comm, x, diam, ids, L, alpha, eps=1.0, phi=np.nan):
    """The JamNetwork of a state from any distribution of its particles (rows ``x``, ``diam``,
    global ``ids``; collective).  ``phi`` is recorded as given."""
    st = slab_state(comm, x, diam, ids, L)
    return network(st, alpha, eps, phi)


def network(st, alpha, eps=1.0, phi=np.nan):
    """The JamNetwork of the SlabState ``st`` (collective); see the module doc for the sums."""
    comm, d = st.comm, st.x.shape[1]
    n_own = len(st.ids)
    edges, halo, gid, once = contact_edges(st)
    rattler = remove_rattlers(comm, halo, n_own, d, edges)
    number, lo, hi = renumber(comm, halo, ~rattler)
    lower = ~once
    # -V'(r)/r of every half-edge, computed once: the contact subsets below take their
    # elements (the same values as computing them on each subset; no copies of the half-edges)
    g = -(potential.dV(edges.r, edges.sigma, alpha, eps) / edges.r)
    # energy and stress (network.analyze, network.stress_tensor): each contact once
    energy = potential.energy(edges.r[once], edges.sigma[once], alpha, eps)
    r1, g1 = edges.rij[once], g[once]
    # per contact (g rij_a) rij_b, component by component; summed exactly below
    stress = [(g1 * r1[:, a]) * r1[:, b] for a in range(d) for b in range(d)]
    # forces on the owned particles (network.particle_forces' order); on j from i: g rij
    force = np.zeros((n_own, d))
    i1, i2, r2, g2 = edges.i[once], edges.i[lower], edges.rij[lower], g[lower]
    for a in range(d):
        force[:, a] = (np.bincount(i2, weights=g2 * (-r2[:, a]), minlength=n_own)
                       - np.bincount(i1, weights=g1 * r1[:, a], minlength=n_own))
    del r1, g1, i1, i2, r2, g2
    fnorm = np.sqrt(np.einsum("ij,ij->i", force, force))[~rattler]
    # contacts among non-rattlers, each once, in (i, j) order
    act = once & (number[edges.i] >= 0) & (number[edges.j] >= 0)
    fsum = np.abs(potential.dV(edges.r[act], edges.sigma[act], alpha, eps))
    ksum = potential.d2V(edges.r[act], edges.sigma[act], alpha, eps)
    # the sums over contacts, exact (one allreduce): the same bits on any number of ranks
    sums = exactsum.totals(comm, energy, fsum, ksum, *stress)
    del energy, fsum, ksum, stress, force, g
    stress = np.array(sums[3:]).reshape(d, d)
    nc = comm.allreduce(int(act.sum()))
    volume = st.L ** d
    return JamNetwork(
        d=d, n=comm.allreduce(n_own), n_active=comm.allreduce(hi - lo), n_contacts=nc,
        phi=phi, alpha=float(alpha), eps=float(eps), energy=float(sums[0]),
        stress=stress / volume,
        max_force=comm.allreduce(float(fnorm.max()) if len(fnorm) else 0.0, op=max_op()),
        mean_force=float(sums[1] / nc) if nc else 0.0,
        mean_stiffness=float(sums[2] / nc) if nc else 0.0, state=st, rattler=rattler,
        active=active_edges(edges, number, gid, st.ids, lo, hi, comm.allreduce(hi - lo),
                            ~rattler))


def active_edges(edges, number, gid, ids, lo, hi, n_active, alive):
    """ActiveEdges from the contact half-edges and the active numbers (see its doc)."""
    act = (number[edges.i] >= 0) & (number[edges.j] >= 0)
    up = act & (ids[edges.i] < gid[edges.j])
    down = np.flatnonzero(act & ~up)
    # the contacts whose owned end is the higher, in (lower id, higher id) order
    down = down[np.lexsort((ids[edges.i[down]], gid[edges.j[down]]))]
    take = np.concatenate([np.flatnonzero(up), down])
    return ActiveEdges(n_active, lo, hi, int(up.sum()), number[edges.i[take]],
                       number[edges.j[take]], edges.rij[take], edges.r[take], edges.sigma[take],
                       ids[alive])


def from_packing(comm, pack):
    """The JamNetwork of a packing every rank holds (tests and small systems): each rank starts
    from its row block (active.row_block), as if it had read only that."""
    start, stop = row_block(pack.n, comm)
    return build(comm, pack.pos[start:stop], pack.diam[start:stop],
                 np.arange(start, stop, dtype=np.int64), pack.L, pack.alpha, pack.eps, pack.phi)
