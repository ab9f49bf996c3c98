"""The distributed active network of parjam.net.active together with the positions of this rank's
non-rattlers (the network's ``active_pos``, rows [lo, hi) in order): what the l* cube counts
and the structure factors need beyond the contacts.  Nothing of length N is gathered.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net import active
from parjam.net.system import Packing
from parjam.net.domain import as_mpi


@dataclass
class Sites:
    """This rank's share of a packing's non-rattlers: the network and their positions."""

    net: object  # parjam.net.active.ActiveNetwork
    pos: np.ndarray  # (hi - lo, d) wrapped positions of the owned non-rattlers, rows lo..hi-1
    mean_diameter: float  # <s> over all N particles (rattlers too)

    @property
    def L(self):
        """The (cubic) box edge."""
        return float(self.net.L[0])


def mean_diameter(comm, diam_rows, n):
    """<s> over all particles from every rank's rows (one allreduce)."""
    return float(as_mpi(comm).allreduce(float(np.sum(diam_rows))) / n)


def from_rows(comm, rows):
    """Sites of a packing's rows (a file's row block, parjam.files.rowio.read_rows: no rank reads
    all N rows)."""
    net = active.from_rows(comm, rows)
    return Sites(net, net.active_pos, mean_diameter(comm, rows.diam, rows.n))


def from_packing(comm, pack):
    """Sites of a packing every rank holds (tests, small systems): each rank starts from its
    row block, as parjam.net.active.from_packing does."""
    comm = as_mpi(comm)
    net = active.from_packing(comm, pack)
    start, stop = active.row_block(pack.n, comm)
    return Sites(net, net.active_pos, mean_diameter(comm, pack.diam[start:stop], pack.n))


def build(comm, source):
    """Sites of a packing's rows (``from_rows``), of a Packing every rank holds, or ``source``
    itself if it already is one (collective)."""
    if isinstance(source, Sites):
        return source
    if isinstance(source, Packing):
        return from_packing(comm, source)
    return from_rows(comm, source)
