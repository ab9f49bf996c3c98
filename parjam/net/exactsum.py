"""numpy's sum of an array whose contiguous blocks live on different ranks, bitwise the value
``np.sum`` gives on the whole array on one rank (so the box of a random start and the
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

Exact sums (``partial``, ``value``, ``totals``): where no serial order is to be reproduced, a sum
over particles spread over ranks is made independent of the split by summing exactly.  Each rank
adds its values into an exact fixed-point accumulator (ACC_LEN int64: 32-bit chunks covering
every finite double, and counts of NaN and infinities; the compiled ``parjam_exact_add`` of
parjam/pack/_kernels.c -- blocks of 256 values split exactly on two grids below the block's
largest magnitude, two doubles a block, the rest value by value -- or a numpy fallback with the
same integers), the accumulators are summed
as integers (one MPI_SUM allreduce: exact, in any order), and the total is rounded once to the
nearest double, ties to even: the value math.fsum gives on all the values at once.  The packing
engine's FIRE sums, Newton's energy and the observables of every state are taken this way, so
a packing is the same bits on any number of ranks.
"""

import math

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


# --- exact sums ---------------------------------------------------------------------------------
CHUNKS = 66  # 32-bit chunks (_kernels.c XACC_CHUNKS): chunk k weighs 2^(32 k - 1074)
NAN, PINF, MINF = 66, 67, 68  # counts of NaN, +inf, -inf
ACC_LEN = 69  # int64 per accumulator (XACC_LEN)


def compiled():
    """The compiled accumulator's library (parjam.pack.kernels), or None: the numpy fallback."""
    from parjam.pack import kernels  # the compiled library lives with the packing kernels

    return kernels.library()


def normalise(acc):
    """Carries propagated in place (every chunk but the last into [0, 2^32)): the unique form
    of an accumulator, which sums over ranks without overflow."""
    for k in range(CHUNKS - 1):
        c = acc[k] >> 32
        acc[k] &= 0xFFFFFFFF
        acc[k + 1] += c
    return acc


def partial(values, acc=None):
    """The exact sum of ``values`` (any shape, float64) as a normalised accumulator (added to
    ``acc`` if given, an int64 array of ACC_LEN)."""
    v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    acc = np.zeros(ACC_LEN, dtype=np.int64) if acc is None else acc
    lib = compiled()
    if lib is not None:
        lib.parjam_exact_add(len(v), v, 1, acc)
        return acc
    acc[NAN] += np.count_nonzero(np.isnan(v))
    acc[PINF] += np.count_nonzero(v == np.inf)
    acc[MINF] += np.count_nonzero(v == -np.inf)
    v = v[np.isfinite(v) & (v != 0.0)]
    m, e = np.frexp(v)  # v = m 2^e, 1/2 <= |m| < 1
    a = np.abs(m * 2.0 ** 53).astype(np.int64)  # v = +-a 2^(e - 53), a < 2^53
    sh = e.astype(np.int64) - 53 + 1074  # in units of 2^-1074
    sub = sh < 0  # subnormals: a is a multiple of 2^-sh
    a[sub] >>= -sh[sub]
    sh[sub] = 0
    idx, s = sh >> 5, sh & 31
    sign = np.where(v < 0, -1, 1)
    parts = ((a & ((1 << (32 - s)) - 1)) << s, (a >> (32 - s)) & 0xFFFFFFFF,
             (a >> (32 - s)) >> 32)
    for k, part in enumerate(parts):
        np.add.at(acc, idx + k, sign * part)
    return normalise(acc)


def value(acc):
    """An accumulator's sum rounded to the nearest double, ties to even (NaN if a NaN or both
    infinities were added, else +-inf if one was)."""
    acc = np.ascontiguousarray(acc, dtype=np.int64)
    lib = compiled()
    if lib is not None:
        return float(lib.parjam_exact_value(acc))
    if acc[NAN] or (acc[PINF] and acc[MINF]):
        return math.nan
    if acc[PINF] or acc[MINF]:
        return math.inf if acc[PINF] else -math.inf
    total = sum(int(c) << (32 * k) for k, c in enumerate(acc[:CHUNKS]))
    try:
        return total / (1 << 1074)  # Python's int division is correctly rounded
    except OverflowError:
        return math.inf if total > 0 else -math.inf


def totals(comm, *arrays):
    """math.fsum of each of ``arrays`` over all ranks of ``comm`` (each rank gives its values;
    one allreduce for all of them), as floats: the same bits however the values are split
    over ranks (collective; ``comm`` mpi4py, petsc4py or None for one process)."""
    accs = np.stack([partial(a) for a in arrays]) if arrays else np.zeros((0, ACC_LEN), np.int64)
    if comm is not None and comm.Get_size() > 1:
        mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
        from mpi4py import MPI

        mpi.Allreduce(MPI.IN_PLACE, accs, op=MPI.SUM)
    return [value(a) for a in accs]


def fsum(comm, values):
    """math.fsum of ``values`` over all ranks of ``comm`` (``totals`` of one array)."""
    return totals(comm, values)[0]
