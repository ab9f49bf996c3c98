"""A minimised state of the packing protocol as each rank's rows, and the rows of its packing
file: no rank holds all N positions between FIRE and the file.

The Jammer keeps a state as the force field's block rows: rank r holds the particles with ids
[lo, hi) of its contiguous block (``StateRows``).  Everything ``parjam pack`` writes about the
state comes from those rows:

- the contact network from parjam.pack.jamnet on the slabs (energy, pressure, stress, N', Nc, the
  rattlers; bit-identical to network.analyze on one rank);
- the hexatic order of 2D states (parjam.net.order's psi6) from the half-edges of the neighbours
  closer than 1.25 sigma_ij on the slabs, summed per particle in the serial order, and over
  particles exactly (the same bits on any number of ranks);
- the rows of its file (``packing_rows``: h5md.write_packing's content, docs/reference/file-format.md, which
  parjam.files.rowio.write_packing_rows writes): the rattler flags and every contact (i < j, its
  overlap, force and stiffness) are sent to the rank whose id block holds i and sorted there
  into the file's (i, j) order.

``StateRows.packing()`` still gathers the whole configuration for callers that want it (tests,
``make_jammed``); the protocol itself never calls it.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net import exactsum, potential
from parjam.pack import jamnet
from parjam.net.active import half_edges, home_rows, max_op
from parjam.net.domain import as_mpi
from parjam.net.order import NEIGHBOUR_FACTOR
from parjam.net.system import Packing


@dataclass
class PackingRows:
    """One rank's consecutive rows of a packing file (rank r's follow rank r-1's): particles
    in id order and contacts in the file's order (each contact once over all ranks)."""

    pos: np.ndarray  # (n_r, d), folded into [0, L)
    diam: np.ndarray  # (n_r,)
    species: np.ndarray  # (n_r,) int32
    rattler: np.ndarray  # (n_r,) bool
    contacts: np.ndarray  # (m_r, 2) particle ids i < j
    overlap: np.ndarray  # (m_r,) 1 - r / sigma_ij
    force: np.ndarray  # (m_r,) |V'(r)|
    stiffness: np.ndarray  # (m_r,) V''(r)


@dataclass
class StateRows:
    """This rank's rows [lo, lo + len(x)) of one state (ids in order; rank r's follow r-1's)."""

    comm: object  # petsc4py or mpi4py communicator of the member
    n: int
    L: float
    alpha: float
    eps: float
    phi: float  # the Jammer's phi (system.Packing.phi's value)
    lo: int
    x: np.ndarray  # (n_r, d) positions
    diam: np.ndarray  # (n_r,)
    meta: dict  # per-particle entries (``row_meta``) as rows, the others as they are
    row_meta: frozenset

    @property
    def d(self):
        return self.x.shape[1]

    @property
    def ids(self):
        return np.arange(self.lo, self.lo + len(self.x), dtype=np.int64)

    @property
    def volume(self):
        return self.L ** self.d

    def gather(self, rows):
        """All N values of per-particle ``rows`` on every rank (collective)."""
        return np.concatenate(as_mpi(self.comm).allgather(np.asarray(rows)))

    def packing(self):
        """The whole state as a system.Packing on every rank (collective: a gather)."""
        meta = {k: (self.gather(v) if k in self.row_meta else v) for k, v in self.meta.items()}
        return Packing(self.gather(self.x), self.gather(self.diam), self.L, self.alpha,
                       self.eps, meta)

    def network(self):
        """The state's contact network on the slabs (parjam.pack.jamnet; collective)."""
        return jamnet.build(self.comm, self.x, self.diam, self.ids, self.L, self.alpha,
                            self.eps, self.phi)


def hexatic_order(rows, net):
    """(local <|psi6_j|>, global |<psi6_j>|) of a 2D state (parjam.net.order.hexatic_order's
    definition, its values to round-off); NaN for 3D or no neighbours.  ``net``: the
    state's JamNetwork (its slabs).  Collective."""
    comm = as_mpi(rows.comm)
    if rows.d != 2:
        return float("nan"), float("nan")
    st = net.state
    # neighbours: "contacts" of diameters scaled by NEIGHBOUR_FACTOR (r < 1.25 sigma_ij)
    dmax = comm.allreduce(float(st.diam.max()) if len(st.diam) else 0.0, op=max_op())
    edges, _, gid = half_edges(st.dom, st.x, NEIGHBOUR_FACTOR * st.diam, st.ids,
                               NEIGHBOUR_FACTOR * dmax * (1.0 + 1e-9))
    n_own = len(st.ids)
    upper = st.ids[edges.i] < gid[edges.j]  # the owned end is the pair's lower id
    rij = np.where(upper[:, None], edges.rij, -edges.rij)  # oriented lower -> higher id
    bond = np.exp(6j * np.arctan2(rij[:, 1], rij[:, 0]))
    # the serial sums: first as the lower end (partners ascending), then as the higher
    order = np.lexsort((gid[edges.j], edges.i, ~upper))
    total = np.zeros(n_own, complex)
    np.add.at(total, edges.i[order], bond[order])
    count = np.bincount(edges.i, minlength=n_own)
    has = count > 0
    psi = total[has] / count[has]
    # exact sums (parjam.net.exactsum): the same bits on any number of ranks
    sums = exactsum.totals(comm, np.abs(psi), psi.real, psi.imag)
    count = comm.allreduce(int(has.sum()))
    if count == 0:
        return float("nan"), float("nan")
    mean = np.complex128(complex(sums[1], sums[2])) / np.float64(count)
    return float(sums[0] / count), float(np.abs(mean))


def packing_rows(rows, net):
    """This rank's :class:`PackingRows` of the state's file (collective): its own
    particles, and the contacts whose lower id it holds, in (i, j) order."""
    comm = as_mpi(rows.comm)
    st = net.state
    edges, _, gid, once = jamnet.contact_edges(st)
    # each contact once, its fields taken one at a time (no copy of the whole subset)
    i, j = st.ids[edges.i[once]], gid[edges.j[once]]
    r, sigma = edges.r[once], edges.sigma[once]
    dv = potential.dV(r, sigma, rows.alpha, rows.eps)
    force = np.linalg.norm(-(dv / r)[:, None] * edges.rij[once], axis=1) if len(r) else np.zeros(0)
    values = np.column_stack([j.astype(float), potential.overlap(r, sigma), force,
                              potential.d2V(r, sigma, rows.alpha, rows.eps)])
    del edges, dv, force, r, sigma
    home_i, got = home_rows(comm, rows.n, i, values.reshape(-1, 4))
    home_j = got[:, 0].astype(np.int64)
    order = np.lexsort((home_j, home_i))
    got = got[order]
    rid, rattler = home_rows(comm, rows.n, st.ids, net.rattler.astype(np.int8))
    if not np.array_equal(rid, rows.ids):  # the id blocks of home_rows are the force field's
        raise AssertionError("parjam: state rows and file rows disagree")
    species = rows.meta.get("species")
    species = np.zeros(len(rows.x), np.int32) if species is None else np.asarray(species)
    return PackingRows(
        pos=rows.x, diam=rows.diam, species=species.astype(np.int32),
        rattler=rattler.astype(bool),
        contacts=np.stack([home_i[order], home_j[order]], axis=1).reshape(-1, 2),
        overlap=got[:, 1], force=got[:, 2], stiffness=got[:, 3])
