"""Spatial domain decomposition of a periodic box: the one component that lets every rank hold
only its own particles and a halo of ghosts (LAMMPS' and HOOMD's design, in its simplest form).

The box (edges L, periodic in every direction) is cut into P slabs along axis 0; rank r owns
the particles with bounds[r] <= x_0 < bounds[r + 1].  The bounds sit at the particle-count
quantiles along axis 0, found from a histogram reduced over the ranks, never from a gather, so
no rank holds an array of length N: memory is O(N/P + halo + P).

- ``migrate`` sends every particle (and any per-particle fields) to the rank that owns it;
- ``halo`` plans the ghosts: copies of the particles, of any rank (this one too, for the periodic
  image), within ``width`` of a rank's slab along axis 0.  Ghost positions are *unwrapped* along
  axis 0, so that owned and ghost positions differ by plain subtraction along it; along the other
  axes the minimum image applies (``separation``).  The plan's ``pull`` refreshes any
  per-particle value on the ghosts (positions, diameters, flags), ``push`` sums ghost values back
  onto their owners;
- ``neighbour_pairs`` lists the pairs within a cutoff with at least one owned end.

Slabs along one axis serve while a slab is not much thinner than the halo width (P up to
L / width ~ tens of ranks at 10^6 particles); ghosts then come from several ranks and the
exchange stays correct, only less local.  Communication is mpi4py's buffer Alltoallv of numpy
arrays (zero counts between ranks that are not neighbours).  Everything is deterministic: owned
rows are sorted by global id, ghosts by (global id, shift).
"""

import numpy as np
from scipy.spatial import cKDTree

HIST_BINS_PER_RANK = 64  # bins of the count histogram per rank (bounds within ~1/64 of a slab)


def as_mpi(comm):
    """The mpi4py communicator of ``comm`` (petsc4py or mpi4py)."""
    return comm.tompi4py() if hasattr(comm, "tompi4py") else comm


IN_TURN_TAG = 7301  # point-to-point tag of the blocks sent to the root in turn


def blocks_in_turn(mpi, block, root=0):
    """On ``root``: each rank's ``block`` in rank order (its own included), received one at a
    time as the caller iterates; elsewhere the block is sent and nothing is yielded.  The
    caller must iterate to the end on ``root`` (also on error) so that every send completes."""
    if mpi.Get_rank() != root:
        mpi.send(block, dest=root, tag=IN_TURN_TAG)
        return
    for r in range(mpi.Get_size()):
        yield block if r == root else mpi.recv(source=r, tag=IN_TURN_TAG)


def box_edges(L, d):
    """Box edges as a float array of shape (d,) (a scalar L is a cube)."""
    edges = np.broadcast_to(np.asarray(L, dtype=np.float64), (d,)).copy()
    if not np.all(np.isfinite(edges)) or np.any(edges <= 0):
        raise ValueError(f"box edges must be positive and finite, got {edges}")
    return edges


def _exchange(comm, send, counts):
    """Alltoallv of the rows of ``send`` (grouped by destination, ``counts`` rows to each rank);
    returns the received rows and the receive counts."""
    size = comm.Get_size()
    counts = np.asarray(counts, dtype=np.int64)
    rcounts = np.empty(size, dtype=np.int64)
    comm.Alltoall(counts, rcounts)
    return _exchange_known(comm, send, counts, rcounts), rcounts


def _exchange_known(comm, send, counts, rcounts):
    """Alltoallv when both count vectors are known (a plan's repeated exchange)."""
    send = np.ascontiguousarray(send)
    if send.dtype == bool:
        return _exchange_known(comm, send.view(np.uint8), counts, rcounts).view(bool)
    row = int(np.prod(send.shape[1:], dtype=np.int64))
    recv = np.empty((int(rcounts.sum()),) + send.shape[1:], dtype=send.dtype)
    sc, rc = counts * row, rcounts * row
    sd = np.concatenate(([0], np.cumsum(sc)[:-1]))
    rd = np.concatenate(([0], np.cumsum(rc)[:-1]))
    comm.Alltoallv([send.reshape(-1), (sc, sd)], [recv.reshape(-1), (rc, rd)])
    return recv


class Halo:
    """The ghosts of one rank for fixed owned rows: who sends what to whom, and the images."""

    def __init__(self, comm, send_index, send_counts, recv_counts, order, ids, shift):
        self.comm = comm
        self.send_index = send_index  # owned rows to send, grouped by destination rank
        self.send_counts = send_counts
        self.recv_counts = recv_counts
        self.order = order  # ghost k is received row order[k] (received rows sorted by id)
        self.ids = ids
        self.shift = shift
        self.x = None  # the ghosts' positions (unwrapped along axis 0)
        self.values = None  # per-particle values that came with the plan (``halo(values=)``)

    @property
    def n(self):
        return len(self.ids)

    def pull(self, values_owned):
        """Per-particle values of the owned rows (first axis n_owned) -> the ghosts' values."""
        got = _exchange_known(self.comm, np.asarray(values_owned)[self.send_index],
                              self.send_counts, self.recv_counts)
        return got[self.order]

    def positions(self, x_owned):
        """Ghost positions (unwrapped along axis 0) for the owned positions ``x_owned``, which
        must not have been re-wrapped since the plan was made."""
        return self.pull(x_owned) + self.shift

    def push(self, values_ghost, n_owned):
        """Ghost values (first axis n_ghost) summed onto their owners: an (n_owned, ...) array."""
        values_ghost = np.asarray(values_ghost)
        back = np.empty_like(values_ghost)
        back[self.order] = values_ghost
        got = _exchange_known(self.comm, back, self.recv_counts, self.send_counts)
        out = np.zeros((n_owned,) + values_ghost.shape[1:], dtype=values_ghost.dtype)
        np.add.at(out, self.send_index, got)
        return out


class SlabDomain:
    """Slabs along axis 0 of a periodic box with edges ``L`` on communicator ``comm``."""

    def __init__(self, comm, L, bounds):
        self.comm = as_mpi(comm)
        self.rank, self.size = self.comm.Get_rank(), self.comm.Get_size()
        self.bounds = np.asarray(bounds, dtype=np.float64)
        self.L = np.atleast_1d(np.asarray(L, dtype=np.float64))
        self.d = len(self.L)
        if len(self.bounds) != self.size + 1 or np.any(np.diff(self.bounds) < 0):
            raise ValueError("slab bounds must be P + 1 non-decreasing values")

    @classmethod
    def balanced(cls, comm, L, x_local, shares=None):
        """Bounds at the particle-count quantiles along axis 0 of the positions the ranks hold
        (collective; a histogram of HIST_BINS_PER_RANK * P bins is reduced, nothing gathered):
        rank r's slab holds the fraction ``shares[r]`` of the particles (P values summing to 1,
        the same on every rank; equal shares by default)."""
        comm = as_mpi(comm)
        x_local = np.asarray(x_local, dtype=np.float64)
        if x_local.ndim != 2:
            raise ValueError("positions must be an (n, d) array")
        edges = box_edges(L, x_local.shape[1])
        size = comm.Get_size()
        bounds = np.linspace(0.0, edges[0], size + 1)
        if size > 1:
            nbins = HIST_BINS_PER_RANK * size
            x0 = np.mod(x_local[:, 0], edges[0])
            hist = np.bincount(np.minimum((x0 / edges[0] * nbins).astype(np.int64), nbins - 1),
                               minlength=nbins).astype(np.int64)
            total = np.empty_like(hist)
            comm.Allreduce(hist, total)
            cum = np.concatenate(([0], np.cumsum(total)))
            if cum[-1] > 0:
                if shares is None:
                    targets = cum[-1] * np.arange(1, size) / size
                else:
                    targets = cum[-1] * np.cumsum(np.asarray(shares, dtype=np.float64))[:-1]
                b = np.clip(np.searchsorted(cum, targets, side="right") - 1, 0, nbins - 1)
                frac = (targets - cum[b]) / np.maximum(total[b], 1)
                bounds[1:-1] = (b + frac) * edges[0] / nbins
            bounds = np.maximum.accumulate(bounds)
            bounds[-1] = edges[0]
        return cls(comm, edges, bounds)

    def scaled(self, factor):
        """The same decomposition of the box scaled by ``factor`` (an affine compression)."""
        return SlabDomain(self.comm, self.L * factor, self.bounds * factor)

    def wrap(self, x):
        return np.mod(x, self.L)

    def fold(self, x):
        """``x`` folded into the box as x - L floor(x / L), never below 0: six times faster
        than ``wrap``'s np.mod, which it may differ from in the last bit (both may give L for a
        coordinate a hair below 0, which every search clamps).  The positions a neighbour
        search and ``owner(folded=True)`` take; the same bits on any number of ranks."""
        out = x - self.L * np.floor(x * (1.0 / self.L))
        return np.maximum(out, 0.0, out=out)  # x / L underflows for a denormal x < 0

    def owner(self, x, folded=False):
        """The rank owning each position (wrapped into the box first, unless ``folded``: then
        the caller has, by ``fold``)."""
        x0 = np.asarray(x, dtype=np.float64)[:, 0]
        if not folded:
            x0 = np.mod(x0, self.L[0])
        r = np.searchsorted(self.bounds, x0, side="right") - 1
        return np.clip(r, 0, self.size - 1)

    def imbalance(self, n_local):
        """max / mean particles per rank (collective)."""
        counts = self.comm.allgather(int(n_local))
        mean = sum(counts) / len(counts)
        return max(counts) / mean if mean > 0 else 1.0

    def migrate(self, x, ids, fields=None):
        """Send every row to the rank owning its (wrapped) position; returns (x, ids, fields)
        of this rank's rows, sorted by global id.  ``fields`` maps names to per-particle arrays
        (the same names on every rank).  The ids, positions and float64 fields travel in one
        exchange (the ids' bits in a float64 column), other fields in one each."""
        x = self.wrap(np.asarray(x, dtype=np.float64))
        ids = np.asarray(ids, dtype=np.int64)
        fields = {k: np.asarray(v) for k, v in (fields or {}).items()}
        dest = self.owner(x)
        order = np.argsort(dest, kind="stable")
        counts = np.bincount(dest, minlength=self.size)
        floats = [k for k in sorted(fields) if fields[k].dtype == np.float64]
        rows, cols = pack_columns([ids, x] + [fields[k] for k in floats], len(ids))
        got, rcounts = _exchange(self.comm, rows[order], counts)
        ids_new, x_new, *fl = unpack_columns(got, cols)
        out = dict(zip(floats, fl))
        out.update({k: _exchange_known(self.comm, fields[k][order], counts, rcounts)
                    for k in sorted(fields) if k not in out})
        keep = np.argsort(ids_new, kind="stable")
        return x_new[keep], ids_new[keep], {k: v[keep] for k, v in out.items()}

    def halo(self, x_owned, ids, width, values=None):
        """The ghost plan for the owned rows (positions ``x_owned``, global ``ids``): every
        particle image within ``width`` of this rank's slab along axis 0 (collective, one
        exchange).  Per-particle float64 ``values`` of the owned rows (an array, or a list of
        arrays), if given, come along in the same exchange: ``Halo.values`` are the ghosts' (as
        ``pull`` would give them; a list for a list)."""
        x_owned = np.asarray(x_owned, dtype=np.float64)
        Lx = self.L[0]
        if not 0 <= width < Lx / 2:
            raise ValueError(f"halo width {width} must be below half the box ({Lx / 2})")
        x0 = x_owned[:, 0]
        b_lo, b_hi = self.bounds[self.rank], self.bounds[self.rank + 1]
        low = x0 - width < b_lo
        if (self.size > 1 and np.diff(self.bounds).min() > width
                and (not len(x0) or (x0.min() >= b_lo and x0.max() < b_hi))):
            # every slab wider than the halo and the rows inside this one (a migrated engine):
            # a row near the lower face is a ghost of the rank below, near the upper face of
            # the rank above (across the periodic boundary for the first and last ranks) --
            # the plan of the general search below, in its order, with a few array operations
            r, P = self.rank, self.size
            groups = sorted([((r - 1) % P, Lx if r == 0 else 0.0, np.flatnonzero(low)),
                             ((r + 1) % P, -Lx if r == P - 1 else 0.0,
                              np.flatnonzero(x0 + width > b_hi))], key=lambda g: g[:2])
            idx = np.concatenate([g[2] for g in groups])
            dest = np.concatenate([np.full(len(g[2]), g[0], dtype=np.int64) for g in groups])
            shift = np.concatenate([np.full(len(g[2]), g[1]) for g in groups])
        else:
            idx, dest, shift = self.ghost_rows(x0, width,
                                               np.flatnonzero(low | (x0 + width >= b_hi)))
        counts = np.bincount(dest, minlength=self.size).astype(np.int64)
        parts = [np.asarray(ids, dtype=np.int64).take(idx), shift, x_owned.take(idx, axis=0)]
        several = isinstance(values, (list, tuple))
        if values is not None:  # take: 3x the fancy index's speed on rows
            parts.extend(np.asarray(a, dtype=np.float64).take(idx, axis=0)
                         for a in (values if several else [values]))
        rows, cols = pack_columns(parts, len(idx))
        got, rcounts = _exchange(self.comm, rows, counts)
        g_ids, g_s, g_x, *g_values = unpack_columns(got, cols)
        perm = np.lexsort((g_s, g_ids))
        shifts = np.zeros((len(perm), x_owned.shape[1]))
        shifts[:, 0] = g_s[perm]
        h = Halo(self.comm, idx, counts, rcounts, perm, g_ids[perm], shifts)
        h.x = g_x.take(perm, axis=0) + shifts  # = h.positions(x_owned), no second exchange
        if values is not None:
            h.values = ([a.take(perm, axis=0) for a in g_values] if several
                        else g_values[0].take(perm, axis=0))
        return h

    def ghost_rows(self, x0, width, near=None):
        """(rows, destination rank, shift along axis 0) of every image of the rows ``near`` (all
        by default; coordinates ``x0`` along axis 0) within ``width`` of another slab or of this
        one across the boundary, grouped by destination (by shift -Lx, 0, Lx and row within
        one): the general search of ``halo``.  A row whose reach [x0 - width, x0 + width] lies
        inside this rank's slab is nobody's ghost (nor, the slab being inside [0, Lx), are its
        images at x0 -+ Lx): ``near`` need only hold the rows near the slab's faces."""
        Lx = self.L[0]
        x0 = np.asarray(x0, dtype=np.float64)
        near = np.arange(len(x0)) if near is None else near
        x0 = x0[near]
        idx, dest, shift = [], [], []
        for s in (-Lx, 0.0, Lx):
            xs = x0 + s
            qlo = np.searchsorted(self.bounds[1:], xs - width, side="right")
            qhi = np.searchsorted(self.bounds[:-1], xs + width, side="left") - 1
            qlo, qhi = np.maximum(qlo, 0), np.minimum(qhi, self.size - 1)
            n = np.maximum(qhi - qlo + 1, 0)
            rows = np.repeat(near, n)
            q = np.repeat(qlo, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
            if s == 0.0:
                rows, q = rows[q != self.rank], q[q != self.rank]
            idx.append(rows)
            dest.append(q)
            shift.append(np.full(len(rows), s))
        idx, dest, shift = np.concatenate(idx), np.concatenate(dest), np.concatenate(shift)
        order = np.argsort(dest, kind="stable")
        return idx[order], dest[order], shift[order]

    def separation(self, xa, xb):
        """xb - xa: plain along axis 0 (unwrapped halo), minimum image along the others."""
        r = np.asarray(xb, dtype=np.float64) - np.asarray(xa, dtype=np.float64)
        r[..., 1:] -= self.L[1:] * np.round(r[..., 1:] / self.L[1:])
        return r

    def neighbour_pairs(self, x_owned, halo, cutoff):
        """Pairs (i, j), i < j, of rows of [owned; ghosts] closer than ``cutoff`` with at least
        one owned end (i is then owned), sorted.  Ghost-ghost pairs are another rank's."""
        n_own = len(x_owned)
        pts = np.concatenate([np.asarray(x_owned, dtype=np.float64).reshape(-1, self.L.size),
                              halo.x.reshape(-1, self.L.size)])
        if len(pts) < 2:
            return np.empty((0, 2), dtype=np.int64)
        pts = pts.copy()
        lo = pts[:, 0].min()
        pts[:, 0] -= lo
        span = pts[:, 0].max() + 2.0 * cutoff + 1.0  # no periodic wrap along axis 0
        pts[:, 1:] = np.mod(pts[:, 1:], self.L[1:])
        box = np.concatenate(([span], self.L[1:]))
        pts = np.minimum(pts, np.nextafter(box, 0))  # cKDTree wants [0, box)
        pairs = cKDTree(pts, boxsize=box).query_pairs(cutoff, output_type="ndarray")
        pairs = pairs[pairs[:, 0] < n_own].astype(np.int64)
        return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def pack_columns(parts, n):
    """Per-row arrays (int64 ids or float64 values, any trailing shape) side by side in one
    float64 array of n rows (an int64 column carried as its bits); returns it and the layout
    for ``unpack_columns``."""
    cols, layout = [], []
    for a in parts:
        a = np.asarray(a)
        flat = np.ascontiguousarray(a).reshape(n, int(np.prod(a.shape[1:], dtype=np.int64)))
        if a.dtype == np.int64:
            flat = flat.view(np.float64)
        elif a.dtype != np.float64:
            raise TypeError(f"pack_columns takes int64 or float64 arrays, not {a.dtype}")
        cols.append(flat)
        layout.append((a.dtype, a.shape[1:], flat.shape[1]))
    out = np.empty((n, sum(c.shape[1] for c in cols)))  # each column copied once, bits as they are
    at = 0
    for c in cols:
        out[:, at:at + c.shape[1]] = c
        at += c.shape[1]
    return out, layout


def unpack_columns(rows, layout):
    """The arrays ``pack_columns`` put side by side, from (any selection of) its rows."""
    out, at = [], 0
    for dtype, shape, width in layout:
        block = np.ascontiguousarray(rows[:, at:at + width])
        if dtype == np.int64:
            block = block.view(np.int64)
        out.append(block.reshape((len(rows),) + tuple(shape)))
        at += width
    return out


def send_rows(comm, dest, ids, fields=None):
    """Send row k of ``ids`` and of every per-particle array in ``fields`` to rank ``dest[k]``
    (collective); returns (ids, fields) of the rows received, sorted by id.  The ids and the
    float64 fields travel side by side in one exchange, other fields in one each.  The packing
    engine (parjam.pack.engine) hands particles between its slabs, and its slabs back to
    PETSc's contiguous row blocks, with it."""
    comm = as_mpi(comm)
    dest = np.asarray(dest, dtype=np.int64)
    fields = {k: np.asarray(v) for k, v in (fields or {}).items()}
    order = np.argsort(dest, kind="stable")
    counts = np.bincount(dest, minlength=comm.Get_size())
    floats = [k for k in sorted(fields) if fields[k].dtype == np.float64]
    rows, cols = pack_columns([np.asarray(ids, dtype=np.int64)] + [fields[k] for k in floats],
                              len(dest))
    got, rcounts = _exchange(comm, rows[order], counts)
    ids_new, *fl = unpack_columns(got, cols)
    out = dict(zip(floats, fl))
    out.update({k: _exchange_known(comm, fields[k][order], counts, rcounts)
                for k in sorted(fields) if k not in out})
    keep = np.argsort(ids_new, kind="stable")
    return ids_new[keep], {k: v[keep] for k, v in out.items()}
