"""The particle ids a soft-mode file records, gathered on rank 0 from the ranks that own them
(collective; one rank's block at a time, net.domain.blocks_in_turn): the cut contacts as (i, j)
pairs and the particles the cut leaves localised.  parjam.files.softmodes writes the file."""

import numpy as np

from parjam.net.domain import blocks_in_turn


def cut_pairs(cs, root=0):
    """The q cut contacts as (i, j) particle ids, i < j, rows sorted (on ``root``; None
    elsewhere; collective).  Each cut contact is two half-edges, one on the owner of each end:
    the pair of active numbers is the key that matches them, each end gives its own id."""
    c = cs.cut
    rec = np.stack([np.minimum(c.i, c.j), np.maximum(c.i, c.j), cs.ids[c.i - cs.lo]], axis=1)
    parts = list(blocks_in_turn(cs.comm, rec, root))
    if cs.comm.Get_rank() != root:
        return None
    rec = np.concatenate(parts).reshape(-1, 3)
    rec = rec[np.lexsort((rec[:, 2], rec[:, 1], rec[:, 0]))]
    pairs = np.sort(rec[:, 2].reshape(-1, 2), axis=1)  # both ends of each key, adjacent
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].astype(np.int64)


def localised_ids(cs, root=0):
    """Particle ids of the particles left with fewer than d contacts, ascending (on ``root``;
    collective)."""
    mine = cs.ids[cs.localised_particles - cs.lo]
    parts = list(blocks_in_turn(cs.comm, mine, root))
    return np.sort(np.concatenate(parts)).astype(np.int64) if parts else None
