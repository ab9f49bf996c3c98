"""The distributed active network of parjam.active together with the positions of this rank's
non-rattlers: what the l* cube counts and the structure factors need beyond the contacts.

parjam.active.build routes every particle to the rank that owns its slab
(``SlabDomain.balanced`` of the rows the ranks started with, then ``migrate``) but keeps only
the contacts.  The same deterministic routing, repeated here on the same rows, gives each rank
the wrapped positions of exactly its owned particles (checked against the network's
``owned_ids``); the non-rattlers among them are the network's rows [lo, hi) in order.  Nothing
of length N is gathered: one Alltoallv of this rank's rows.
"""

from dataclasses import dataclass

import numpy as np

from parjam import active, rowio
from parjam.domain import SlabDomain, as_mpi


@dataclass
class Sites:
    """This rank's share of a packing's non-rattlers: the network and their positions."""

    net: object  # parjam.active.ActiveNetwork
    pos: np.ndarray  # (hi - lo, d) wrapped positions of the owned non-rattlers, rows lo..hi-1
    mean_diameter: float  # <s> over all N particles (rattlers too)

    @property
    def L(self):
        """The (cubic) box edge."""
        return float(self.net.L[0])


def owned_positions(comm, x, ids, L, net):
    """Positions of the network's owned non-rattlers, routed from the rows ``x`` (global
    ``ids``) that this rank passed to parjam.active.build (collective)."""
    dom = SlabDomain.balanced(comm, L, x)
    xo, got, _ = dom.migrate(x, ids)
    if not np.array_equal(got, net.owned_ids):
        raise RuntimeError("the positions were not routed as the network's particles")
    return xo[~net.rattler]


def mean_diameter(comm, diam_rows, n):
    """<s> over all particles from every rank's rows (one allreduce)."""
    return float(as_mpi(comm).allreduce(float(np.sum(diam_rows))) / n)


def from_rows(comm, rows):
    """Sites of a packing file's rows (parjam.rowio.read_rows): no rank reads all N rows."""
    net = rowio.network(comm, rows)
    return Sites(net, owned_positions(comm, rows.pos, rows.ids, rows.L, net),
                 mean_diameter(comm, rows.diam, rows.n))


def from_packing(comm, pack):
    """Sites of a packing every rank holds (tests, small systems): each rank starts from its
    row block, as parjam.active.from_packing does."""
    comm = as_mpi(comm)
    net = active.from_packing(comm, pack)
    start, stop = active.row_block(pack.n, comm)
    ids = np.arange(start, stop, dtype=np.int64)
    return Sites(net, owned_positions(comm, pack.pos[start:stop], ids, pack.L, net),
                 mean_diameter(comm, pack.diam[start:stop], pack.n))


def build(comm, source):
    """Sites of a rowio.Rows, of a Packing every rank holds, or ``source`` itself if it
    already is one (collective)."""
    if isinstance(source, Sites):
        return source
    if isinstance(source, rowio.Rows):
        return from_rows(comm, source)
    return from_packing(comm, source)
