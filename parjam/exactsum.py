"""numpy's sum of an array whose contiguous blocks live on different ranks, bitwise the value
``np.sum`` gives on the whole array on one rank (issue 18: the box of a random start and the
Jammer's sphere volume are then the serial ones on any number of ranks, with no rank holding N
values).

numpy sums a contiguous float64 array pairwise (numpy's ``pairwise_sum``, checked bitwise against
``np.add.reduce`` on this numpy in tests/test_randomstart.py): a segment of at most BLOCK values
is a leaf, summed by eight interleaved accumulators; a longer one is split at half its length
rounded down to a multiple of eight and the two halves' sums are added.  The tree depends on the
length only, so every rank walks the same one: it sums the nodes that lie wholly in its block
(``np.add.reduce`` of the slice: numpy's own value of that node), hands over its share of the
at most two leaves that straddle its block's ends, and after one allgather of these O(log N +
BLOCK) numbers every rank adds the nodes in the tree's order.
"""

import numpy as np

BLOCK = 128  # numpy's PW_BLOCKSIZE: the longest segment summed as one leaf


def halves(s, e):
    """The two children of tree node [s, e) (longer than BLOCK)."""
    half = (e - s) // 2
    half -= half % 8
    return (s, s + half), (s + half, e)


def local_nodes(values, lo, n):
    """(node sums, leaf pieces) of the block [lo, lo + len(values)) of n values: the sums of
    the maximal tree nodes inside the block {(s, e): sum}, and the block's part of every leaf
    that crosses its ends {(s, e): (first index, values)}."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    hi = lo + len(values)
    sums, pieces = {}, {}
    todo = [(0, n)]
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


def combine(sums, pieces, n):
    """The total of the tree from every rank's node sums and leaf pieces (lists of dicts)."""
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

    return node(0, n)


def total(comm, values, lo, n):
    """np.sum of the n values whose block [lo, lo + len(values)) this rank holds, as an
    np.float64, bitwise the serial one (collective over the mpi4py or petsc4py ``comm``; None
    or one rank: the local sum)."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    if comm is None or comm.Get_size() == 1:
        if len(values) != n:
            raise ValueError(f"one rank holds {len(values)} of {n} values")
        return np.add.reduce(values)
    if n == 0:
        return np.float64(0.0)
    mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    parts = mpi.allgather(local_nodes(values, lo, n))
    return combine([p[0] for p in parts], [p[1] for p in parts], n)
