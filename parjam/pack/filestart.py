"""The start of ``parjam pack --from FILE`` by rows: no rank reads or holds all N
particles of the file.

Every rank holds only its contiguous block of rows of the file (read and validated by
parjam.files.rowio.read_rows: the split of PETSc's rows, the Jammer's block).  The small
description the command needs before any work (d, N, the volume fraction, the dispersity label
and diameter ratio) is made once, from those rows, by reductions:

- phi is system.Packing.phi's value bitwise: the sphere volumes summed as numpy sums the whole
  array (parjam.net.exactsum), divided by L^d;
- the dispersity is read_packing's ``len(set(diameters))`` (1 mono, 2 bi, more poly) from
  each rank's distinct values (at most three are needed to tell), and the ratio max / min by
  two reductions;
- coinciding centres, which read_packing finds with a k-d tree of all N, are looked for on the
  slabs of parjam.net.domain within DUPLICATE_TOL x the smallest diameter (a halo that thin holds
  almost nothing); on one rank, which holds all rows anyway, by read_packing's own search
  (system.coinciding_pairs).

The Jammer then starts from ``start_rows``: this rank's rows as staterows.StateRows, the same
rows, metadata and phi that ``Jammer(comm, pack)`` took from the whole file (the old path),
so the packings made are bitwise those of the whole-file start.
"""

import os
from dataclasses import dataclass

import numpy as np

from parjam.errors import ParjamError
from parjam.net import exactsum
from parjam.net.active import max_op, min_op
from parjam.net.domain import SlabDomain, as_mpi
from parjam.pack.staterows import StateRows
from parjam.net.system import DUPLICATE_TOL, coinciding_pairs, sphere_volume


@dataclass(frozen=True)
class Description:
    """What ``pack --from`` takes from the file before any work (the same on every rank)."""

    d: int
    n: int
    phi: float  # system.Packing.phi of the whole file, bitwise
    dispersity: str  # mono, bi or poly, as read_packing's distinct diameters say
    ratio: float  # largest / smallest diameter


def dispersity_label(comm, diam):
    """read_packing's label of ``len(set(all diameters))`` from this rank's rows (collective):
    1 distinct value mono, 2 bi, more poly."""
    mine = np.unique(diam)[:3]  # three distinct values already make it poly
    seen = np.unique(np.concatenate(comm.allgather(mine)))
    return {1: "mono", 2: "bi"}.get(len(seen), "poly")


def duplicate_problem(comm, rows):
    """read_packing's refusal of coinciding centres (closer than DUPLICATE_TOL x the smallest
    diameter), found on the slabs: the message naming the first pair (i < j) and how many there
    are, or None (collective)."""
    dmin = comm.allreduce(float(rows.diam.min()) if len(rows.diam) else np.inf, op=min_op())
    cut = DUPLICATE_TOL * dmin
    if comm.Get_size() == 1:  # read_packing's own search (no slab copies of the positions)
        found = coinciding_pairs(rows.pos, rows.diam, rows.L)
        lo, hi = found[:, 0], found[:, 1]
    else:
        dom = SlabDomain.balanced(comm, rows.L, rows.pos)
        x, ids, _ = dom.migrate(rows.pos, rows.ids)
        halo = dom.halo(x, ids, cut)
        found = dom.neighbour_pairs(x, halo, cut)
        gid = np.concatenate([ids, halo.ids])
        i, j = gid[found[:, 0]], gid[found[:, 1]]
        # an owned-ghost pair is found by both ranks: counted where the owned end is the smaller
        keep = (found[:, 1] < len(x)) | (i < j)
        lo, hi = np.minimum(i, j)[keep], np.maximum(i, j)[keep]
    count = comm.allreduce(int(len(lo)))
    if count == 0:
        return None
    first = min((p for p in comm.allgather(min(zip(lo.tolist(), hi.tolist()), default=None))
                 if p is not None))
    return (f"{rows.path}: particles {first[0]} and {first[1]} coincide ({count} duplicated "
            f"pair(s))")


def describe(comm, rows):
    """Describe a packing from every rank's block of its rows (``rows``: parjam.files.rowio's
    read_rows of the file; collective over the petsc4py or mpi4py ``comm``); coinciding centres
    are one ParjamError, raised on every rank."""
    mpi = as_mpi(comm)
    problems = [p for p in mpi.allgather(duplicate_problem(mpi, rows)) if p]
    if problems:
        raise ParjamError(problems[0])
    volume = exactsum.total(mpi, sphere_volume(rows.diam, rows.d), rows.start, rows.n)
    ends = np.array([-rows.diam.min(), rows.diam.max()] if len(rows.diam) else [-np.inf] * 2)
    mpi.Allreduce(ends.copy(), ends, op=max_op())
    return Description(rows.d, rows.n, float(volume / rows.L ** rows.d),
                       dispersity_label(mpi, rows.diam), float(ends[1] / -ends[0]))


def start_rows(comm, rows, alpha, phi):
    """This rank's block ``rows`` of a packing file (described by ``describe`` before) as
    staterows.StateRows, with the potential exponent ``alpha`` and the file's ``phi`` (from
    ``describe``): what ``Jammer(comm, pack)`` made of the whole file, row for row."""
    meta = {"species": None if rows.species is None else rows.species.astype(np.int32),
            "source": os.path.abspath(rows.path)}
    return StateRows(comm, rows.n, rows.L, alpha, rows.eps, phi, rows.start, rows.pos, rows.diam,
                     meta, frozenset({"species"} if rows.species is not None else ()))
