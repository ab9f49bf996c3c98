"""numpy's sum of an array whose contiguous blocks live on different ranks, bitwise the value
``np.sum`` gives on the whole array on one rank (issue 18: the box of a random start and the
Jammer's sphere volume are then the serial ones on any number of ranks, with no rank holding N
values).

How numpy sums a contiguous float64 array (checked bitwise against ``np.add.reduce`` on this
numpy in tests/pack/test_randomstart.py): in chunks of ``np.getbufsize()`` values (8192), added in
turn to a running total from 0; each chunk pairwise (numpy's ``pairwise_sum``): a segment of at
most BLOCK values is a leaf, summed by eight interleaved accumulators, a longer one is split at
half its length rounded down to a multiple of eight and the halves' sums added.

Across ranks: every chunk belongs to the rank holding its first value.  A chunk inside one
rank's block is summed there (``np.add.reduce`` of the slice is numpy's own value of it).  For
the at most two chunks that cross a rank's block ends, the rank sums the tree nodes that lie
wholly in its block and hands over its share of the at most two leaves that cross them
(O(log chunk + BLOCK) numbers); one allgather of these lets the owners add those chunks' nodes
in the tree's order.  The chunk sums are then added in turn along the ranks (one number passed
from rank to rank), as numpy adds them, and the total broadcast.
"""

import numpy as np

BLOCK = 128  # numpy's PW_BLOCKSIZE: the longest segment summed as one leaf


def chunk_length():
    """numpy's reduction chunk: its buffer size."""
    return int(np.getbufsize())


def halves(s, e):
    """The two children of tree node [s, e) (longer than BLOCK)."""
    half = (e - s) // 2
    half -= half % 8
    return (s, s + half), (s + half, e)


def local_nodes(values, lo, s0, e0):
    """This block's share of the pairwise tree of segment [s0, e0): the sums of the maximal
    nodes inside the block [lo, lo + len(values)) {(s, e): sum}, and its part of every leaf that
    crosses its ends {(s, e): (first index, values)}."""
    hi = lo + len(values)
    sums, pieces = {}, {}
    todo = [(s0, e0)]
    while todo:
        s, e = todo.pop()
        if e <= lo or s >= hi or s == e:
            continue
        if lo <= s and e <= hi:
            sums[(s, e)] = np.add.reduce(values[s - lo:e - lo])
        elif e - s <= BLOCK:
            a, b = max(s, lo), min(e, hi)
            pieces[(s, e)] = (a, values[a - lo:b - lo].copy())
        else:
            todo.extend(halves(s, e))
    return sums, pieces


def combine(sums, pieces, s0, e0):
    """The pairwise sum of segment [s0, e0) from the blocks' node sums and leaf pieces (lists of
    ``local_nodes``' dicts)."""
    known = {k: v for part in sums for k, v in part.items()}
    leaves = {}
    for part in pieces:
        for k, piece in part.items():
            leaves.setdefault(k, []).append(piece)

    def node(s, e):
        if (s, e) in known:
            return known[(s, e)]
        if e - s <= BLOCK:
            parts = sorted(leaves[(s, e)], key=lambda p: p[0])
            return np.add.reduce(np.concatenate([p[1] for p in parts]))
        left, right = halves(s, e)
        return node(*left) + node(*right)

    return node(s0, e0)


def crossing_chunks(lo, hi, n, chunk):
    """The chunks [s, e) of n values that hold some of [lo, hi) but not all of theirs."""
    out = []
    for k in {lo // chunk, (hi - 1) // chunk} if hi > lo else ():
        s, e = k * chunk, min((k + 1) * chunk, n)
        if s < lo or e > hi:
            out.append((s, e))
    return out


def total(comm, values, lo, n):
    """np.sum of the n values whose block [lo, lo + len(values)) this rank holds (the blocks
    of the ranks in rank order tile [0, n)), as an np.float64 bitwise the serial one
    (collective over the mpi4py or petsc4py ``comm``; None or one rank: the local sum)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if comm is None or comm.Get_size() == 1:
        if len(values) != n:
            raise ValueError(f"one rank holds {len(values)} of {n} values")
        return np.add.reduce(values)
    mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    rank, size = mpi.Get_rank(), mpi.Get_size()
    chunk, hi = chunk_length(), lo + len(values)
    shares = {c: local_nodes(values, lo, *c) for c in crossing_chunks(lo, hi, n, chunk)}
    everyone = mpi.allgather(shares)
    running = np.float64(0.0) if rank == 0 else mpi.recv(source=rank - 1, tag=77)
    for s in range(-(-lo // chunk) * chunk, hi, chunk):  # the chunks starting in the block
        e = min(s + chunk, n)
        if e <= hi:
            running = running + np.add.reduce(values[s - lo:e - lo])
        else:
            parts = [share[(s, e)] for share in everyone if (s, e) in share]
            running = running + combine([p[0] for p in parts], [p[1] for p in parts], s, e)
    if rank < size - 1:
        mpi.send(running, dest=rank + 1, tag=77)
    return mpi.bcast(running, root=size - 1)
