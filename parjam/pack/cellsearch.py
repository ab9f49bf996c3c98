"""The neighbour searches of the packing engine by linked cells, in compiled code
(``_kernels.c``, loaded by parjam.pack.kernels): the fully periodic box's (one rank) and a
slab's with its halo (several ranks), both giving the pairs in the global (i, j) order the force
sums need, each pair within the cutoff or, given the diameters, within its own reach
(d_i + d_j) / 2 + skin; a k-d tree serves when there is no compiled library."""

import numpy as np

from parjam.pack import kernels


def cell_pairs(pos, L, cutoff, lo, hi):
    """The pairs i < j with |x_j - x_i| <= cutoff (minimum image) and i or j in [lo, hi),
    sorted by (i, j), from a cell search in compiled code over positions ``pos`` folded
    into [0, L) (all n, (n, d)).  None when there is no compiled library or the box holds fewer
    than 3 cells of edge >= cutoff per direction (then parjam.net.system's k-d tree serves)."""
    got = cell_pair_lists(pos, L, cutoff, lo, hi)
    return None if got is None else np.stack(got, axis=1)


class Scratch:
    """Work arrays of the neighbour searches, kept from one rebuild to the next (an engine
    holds one): a rebuild then writes into memory already mapped instead of faulting in fresh
    pages (a tenth of a search's time).  Arrays grow, never shrink; their contents are
    meaningless between calls."""

    def __init__(self):
        self.arrays = {}

    def get(self, name, n, dtype=np.int64, width=1):
        """An array of n rows (n x width for width > 1) of ``dtype``, C-contiguous."""
        need = n * width
        a = self.arrays.get(name)
        if a is None or len(a) < need or a.dtype != dtype:
            a = self.arrays[name] = np.empty(max(need, int(1.25 * need)) + 16, dtype=dtype)
        a = a[:need]
        return a.reshape(n, width) if width > 1 else a


def cell_search_applies(n, d, L, cutoff):
    """Whether ``cell_pair_lists`` serves n points in d dimensions (the compiled library, at
    least 3 cells of edge >= cutoff a side, not many more cells than points)."""
    nc = int(L // cutoff) if cutoff > 0 else 0
    return kernels.library() is not None and nc >= 3 and d in (2, 3) and nc ** d <= 8 * n + 1000


def reach_of(diam, skin):
    """The diameters of the points as a search's per-pair reach wants them (C-contiguous
    float64, or None: every pair within the cutoff) and the skin (0 without diameters)."""
    if diam is None:
        return None, 0.0
    return np.ascontiguousarray(diam, dtype=np.float64), float(skin)


def cell_pair_lists(pos, L, cutoff, lo, hi, cap=None, scratch=None, diam=None, skin=0.0):
    """cell_pairs as two arrays (pi, pj) (the engine's form on one rank); ``cap``: the expected
    number of pairs (more are found by a second pass); ``scratch``: a Scratch for the work
    arrays (fresh ones if None).  The search covers the whole box (half stencil,
    ``parjam_cell_pairs``); for a part [lo, hi) of the rows the pairs touching it are kept.
    Given the diameters ``diam``, only the pairs within their own reach
    (d_i + d_j) / 2 + ``skin`` (which must not exceed ``cutoff``) are listed: a Verlet list
    that holds each pair to its own contact distance plus the skin (a third shorter for the
    1 : 1.4 mixtures).  None where it does not apply (``cell_search_applies``)."""
    n, d = pos.shape
    if not cell_search_applies(n, d, L, cutoff):
        return None
    lib = kernels.library()
    nc = int(L // cutoff)
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    diam, skin = reach_of(diam, skin)
    work = Scratch() if scratch is None else scratch
    start = work.get("start", nc ** d + 1)
    order, cellof = work.get("order", n), work.get("cellof", n)
    sp, off = work.get("sp", n, np.float64, d), work.get("off", n + 1)
    sh = work.get("sh", n, np.float64)
    cap = 20 * n + 1024 if cap is None else int(cap)
    while True:
        ta, tb = work.get("ta", cap), work.get("tb", cap)
        pi, pj = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
        got = lib.parjam_cell_pairs(n, d, pos, L, cutoff, nc,
                                    None if diam is None else diam.ctypes.data, skin, start,
                                    order, cellof, sp, sh, off, cap, ta, tb, pi, pj)
        if got >= 0:
            break
        cap = -got
    pi, pj = pi[:got], pj[:got]
    if lo > 0 or hi < n:
        keep = ((pi >= lo) & (pi < hi)) | ((pj >= lo) & (pj < hi))
        return pi[keep], pj[keep]
    if got < 0.7 * cap:  # a loose first guess: no idle capacity kept
        return pi.copy(), pj.copy()
    return pi, pj


def slab_pairs(pos, L, cutoff, row, gid, kind, low, cap=None, scratch=None, slab=None,
               diam=None, skin=0.0):
    """The pairs of one slab's search points (parjam.pack.engine): ``pos`` (n, d) open along axis 0,
    folded into [0, L) along the others; ``kind`` 0 for owned particles, 1 for images of owned
    ones across the periodic boundary, 2 for other ranks' ghosts; ``low`` the points of kinds 0
    and 2 in global-id order.  Returns (pi, pj), rows ``row[.]`` of the pairs closer than
    ``cutoff`` with an owned end, each physical pair once, in global (i, j) order (see
    ``parjam_slab_pairs``).  ``cap``: the expected number of pairs (e.g. the last list's, with
    a margin; more are found by a second pass); ``scratch``: a Scratch for the work arrays;
    ``slab``: the slab's (lower, upper) bounds along axis 0, to which the layers of cells are
    then aligned, the halo on each side in a layer of its own (its ghosts' pairs among
    themselves are not searched: 8 - 13 % of a search at N = 65,536 - 16,384 on 2 ranks).
    ``diam``: the points' diameters, to list only the pairs within their own reach
    (d_a + d_b) / 2 + ``skin`` <= ``cutoff`` (as ``cell_pair_lists``).
    The pairs and their order do not depend on the cells.  Compiled cells; the numpy fallback
    uses a k-d tree."""
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    n, d = pos.shape
    row, gid, kind, low = (np.ascontiguousarray(a, dtype=np.int64) for a in (row, gid, kind, low))
    if n == 0:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    x0min = float(pos[:, 0].min())
    span = float(pos[:, 0].max()) - x0min
    w = cutoff
    while True:  # cells of edge >= cutoff, at most ~4 per point (a dilute box: coarser cells)
        nc = max(1, int(L // w))
        nx = max(1, int(span // w))
        if nx * nc ** (d - 1) <= 4 * n + 64:
            break
        w *= 1.25
    w0 = span / nx * (1.0 + 1e-12) if span > 0 else 1.0
    if slab is not None and slab[1] - slab[0] >= w:
        # layers of edge >= w: k across the slab, one below and one above it for the halo
        k = int((slab[1] - slab[0]) // w)
        a0 = (slab[1] - slab[0]) / k * (1.0 + 1e-12)
        if x0min >= slab[0] - a0 and x0min + span < slab[0] + (k + 1) * a0:
            x0min, w0, nx = slab[0] - a0, a0, k + 2
    lib = kernels.library()
    if lib is None:
        kernels.fallback()
        return slab_pairs_numpy(pos, L, cutoff, row, gid, kind, low, diam, skin)
    work = Scratch() if scratch is None else scratch
    start = work.get("start", nx * nc ** (d - 1) + 1)
    order, cellof = work.get("order", n), work.get("cellof", n)
    sp, sg, place = work.get("sp", n, np.float64, d), work.get("sg", n), work.get("place", n)
    sh = work.get("sh", n, np.float64)
    diam, skin = reach_of(diam, skin)
    off = work.get("off", len(low) + 1)
    # room for the pairs found before the ones without an owned end are dropped
    cap = 10 * n + 1024 if cap is None else int(1.1 * cap) + 1024
    while True:
        ta, tb = work.get("ta", cap), work.get("tb", cap)
        pi, pj = np.empty(cap, dtype=np.int64), np.empty(cap, dtype=np.int64)
        got = lib.parjam_slab_pairs(n, d, pos, L, cutoff, x0min, w0, nx, nc,
                                    None if diam is None else diam.ctypes.data, skin, row, gid,
                                    kind, len(low), low, start, order, cellof, sp, sh, sg, place,
                                    off, cap, ta, tb, pi, pj)
        if got >= 0:
            if got < 0.7 * cap:  # a loose first guess: no idle capacity kept
                return pi[:got].copy(), pj[:got].copy()
            return pi[:got], pj[:got]
        cap = -got



def slab_pairs_numpy(pos, L, cutoff, row, gid, kind, low, diam=None, skin=0.0):
    """slab_pairs by a k-d tree (the same pairs in the same order)."""
    from scipy.spatial import cKDTree

    pts = pos.copy()
    pts[:, 0] -= pts[:, 0].min()
    box = np.concatenate(([pts[:, 0].max() + 2.0 * cutoff + 1.0], np.full(pos.shape[1] - 1, L)))
    pts = np.minimum(pts, np.nextafter(box, 0))
    pr = cKDTree(pts, boxsize=box).query_pairs(cutoff, output_type="ndarray").astype(np.int64)
    a, b = pr[:, 0], pr[:, 1]
    swap = gid[a] > gid[b]
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    keep = (gid[a] < gid[b]) & (kind[a] != 1) & ((kind[a] == 0) | (kind[b] == 0))
    a, b = a[keep], b[keep]
    if diam is not None:  # each pair within its own reach, as the compiled search keeps it
        dx = pos[b] - pos[a]
        dx[:, 1:] -= L * np.rint(dx[:, 1:] / L)
        h = 0.5 * np.asarray(diam, dtype=np.float64)
        c = (h[a] + skin) + h[b]
        near = np.einsum("ij,ij->i", dx, dx) <= c * c
        a, b = a[near], b[near]
    place = np.empty(len(gid), dtype=np.int64)
    place[low] = np.arange(len(low))
    o = np.lexsort((gid[b], place[a]))
    return row[a[o]], row[b[o]]
