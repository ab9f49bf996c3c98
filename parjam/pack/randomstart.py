"""The random (infinite-temperature) start of a packing: uniform positions at a volume fraction,
the diameters of a dispersity, the particles numbered cell by cell; made by row blocks, so that
for a member shared by P ranks no rank holds an array of length N.

The configuration is the serial one bitwise on any number of ranks:

- numpy's PCG64 Generator spends one 64-bit word per double of ``random`` and of ``uniform``
  (checked in tests/pack/test_randomstart.py), so the member's stream is a row of draw indices:
  the poly diameters take draws [0, N), the positions draws [N0, N0 + N d) row by row (N0 = N
  for poly, 0 otherwise).  Rank r makes the particles of its block [a, b) of draw indices from
  a copy of the stream advanced to them (``draw_rows``);
- the box edge comes from the sum of the sphere volumes in draw order, summed as numpy sums the
  whole array (parjam.net.exactsum), so L is bitwise the serial one;
- the spatial numbering (``spatial_order``: cells of edge >= 2 d_max in lexicographic order,
  ties in draw order) is made without a global sort (``spatial_rows``): each row goes to a rank
  by a histogram of its (cell key, draw index) reduced over the ranks, is sorted there, gets its
  new id from an exclusive scan of the counts, and is sent to the rank whose block of PETSc's
  contiguous rows (parjam.net.active.row_block, the split of the Jammer's force field) holds that id.

``random_packing`` (a whole system.Packing, for a member on one rank, tests and scripts) is the
same code on one rank.
"""

import numpy as np

from parjam.net import exactsum
from parjam.net.active import max_op, row_block
from parjam.net.domain import as_mpi, send_rows
from parjam.errors import ParjamError
from parjam.pack.protocol import DEFAULT_ALPHA, DEFAULT_RATIO, DISPERSITIES
from parjam.pack.staterows import StateRows
from parjam.net.system import Packing, sphere_volume

BINS_PER_RANK = 64  # histogram bins of the (cell key, draw) order per rank (balance ~1/64)


def member_rng(seed, member):
    """Independent, reproducible stream for member m, whatever the number of ranks."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(member)]))


def check_dispersity(dispersity, ratio):
    if dispersity not in DISPERSITIES:
        raise ParjamError(f"unknown dispersity {dispersity!r}; choose from "
                          f"{', '.join(DISPERSITIES)}")
    if dispersity != "mono" and (not np.isfinite(ratio) or ratio < 1.0):
        raise ParjamError(f"diameter ratio must be >= 1, got {ratio}")


def diameter_draws(n, dispersity):
    """Draws of the stream the diameters of n particles take (poly: one per particle)."""
    return n if dispersity == "poly" else 0


def stream_at(rng, draws):
    """A Generator on a copy of ``rng``'s bit generator, advanced by ``draws`` 64-bit words
    (``rng`` is not touched)."""
    bg = type(rng.bit_generator)()
    bg.state = rng.bit_generator.state
    bg.advance(int(draws))
    return np.random.Generator(bg)


def diameter_rows(a, b, n, dispersity, ratio, rng):
    """Diameters and species of the particles with draw indices [a, b) of n, the smallest
    diameter 1: mono; bi (50:50, the first n // 2 small, large/small = ratio); poly (uniform
    between 1 and ratio, draws [0, n) of the stream)."""
    check_dispersity(dispersity, ratio)
    if dispersity == "mono":
        return np.ones(b - a), np.zeros(b - a, dtype=np.int32)
    if dispersity == "bi":
        species = (np.arange(a, b) >= n // 2).astype(np.int32)
        return np.where(species == 1, ratio, 1.0), species
    return 1.0 + (ratio - 1.0) * stream_at(rng, a).random(b - a), np.zeros(b - a, np.int32)


def position_rows(a, b, n, d, L, dispersity, rng):
    """Uniform positions in [0, L)^d of the particles with draw indices [a, b) (one draw per
    coordinate, row by row, after the diameters'); a draw that rounds to L is put at 0."""
    pos = stream_at(rng, diameter_draws(n, dispersity) + a * d).uniform(0.0, L, size=(b - a, d))
    pos[pos >= L] = 0.0
    return pos


def cells_per_side(L, cell):
    """Cells a side of edge >= ``cell`` (at least one)."""
    return max(1, int(L // cell))


def cell_keys(pos, L, m):
    """Lexicographic index of the cell of each position (m cells a side; the first
    coordinate's cell is the most significant digit)."""
    idx = np.minimum((pos / L * m).astype(np.int64), m - 1)
    key = np.zeros(len(pos), dtype=np.int64)
    for k in range(pos.shape[1]):
        key = key * m + idx[:, k]
    return key


def spatial_order(pos, L, cell):
    """Permutation that numbers the particles cell by cell (cells of edge >= ``cell``, in
    lexicographic order, ties in the given order): neighbours get nearby indices, so the force
    kernel and the matrices touch nearby memory, and the contiguous row blocks of the MPI ranks
    are compact slabs with few couplings between ranks.  A 3D N = 10^5 force evaluation costs
    12 ms instead of 21 ms in random order.  The particles are independent and identically
    placed, so this is the same random configuration."""
    return np.argsort(cell_keys(pos, L, cells_per_side(L, cell)), kind="stable")


def order_bins(key, draw, n_keys, n, nbins):
    """Bin of each (cell key, draw index) among ``nbins``, non-decreasing in that lexicographic
    order (integer arithmetic): by key where there are more keys than bins, else each key's
    bins split by draw index (a box of few cells).  Uniform positions fill them evenly."""
    if n_keys >= nbins:
        return key * nbins // n_keys
    per = nbins // n_keys
    return key * per + draw * per // max(n, 1)


def block_starts(comm, n):
    """First id of every rank's block of PETSc's contiguous rows, and n (length P + 1)."""
    return np.array(as_mpi(comm).allgather(row_block(n, comm)[0]) + [n], dtype=np.int64)


def spatial_rows(comm, lo, x, fields, L, dmax, n):
    """The distributed ``spatial_order``: rows [lo, lo + len(x)) in draw order (positions
    ``x``, per-particle ``fields``) -> this rank's block of PETSc's contiguous rows of the
    numbered configuration (x, fields), the same permutation as ``spatial_order`` on the whole
    array (collective; no rank holds more than O(N/P) rows)."""
    size = 1 if comm is None else as_mpi(comm).Get_size()
    m = cells_per_side(L, 2.0 * dmax)
    key = cell_keys(x, L, m)
    if size == 1:
        order = np.argsort(key, kind="stable")
        return x[order], {k: np.asarray(v)[order] for k, v in fields.items()}
    mpi = as_mpi(comm)
    draw = np.arange(lo, lo + len(x), dtype=np.int64)
    nbins = BINS_PER_RANK * size
    bins = order_bins(key, draw, m ** x.shape[1], n, nbins)
    hist = np.bincount(bins, minlength=nbins).astype(np.int64)
    mpi.Allreduce(hist.copy(), hist)
    starts = block_starts(comm, n)
    # a bin goes to the rank whose block holds its first particle: sorted ranges of the order
    home = np.searchsorted(starts, np.cumsum(hist) - hist, side="right") - 1
    dest = np.minimum(home[bins], size - 1)
    del key, bins  # (the receiver recomputes the keys of its rows)
    _, got = send_rows(mpi, dest, draw, dict(fields, x=x))  # back sorted by draw index
    del dest, draw
    order = np.argsort(cell_keys(got["x"], L, m), kind="stable")  # by (key, draw)
    got = {k: v[order] for k, v in got.items()}
    first = mpi.exscan(len(order)) or 0
    new = first + np.arange(len(order), dtype=np.int64)
    del order
    ids, out = send_rows(mpi, np.searchsorted(starts, new, side="right") - 1, new, got)
    a, b = row_block(n, comm)
    if not np.array_equal(ids, np.arange(a, b)):
        raise AssertionError("parjam: the spatial order lost or repeated a particle")
    return out.pop("x"), out


def start_rows(comm, d, n, phi, alpha=DEFAULT_ALPHA, dispersity="mono", ratio=DEFAULT_RATIO,
               rng=None, eps=1.0):
    """This rank's block rows (staterows.StateRows, the ids of parjam.net.active.row_block: the
    Jammer's) of the random start of ``random_packing``: the same configuration bitwise, made
    without any rank holding N particles (collective over ``comm``, petsc4py or mpi4py; None:
    one rank).  ``rng`` is left advanced past every draw, as a serial start leaves it."""
    check_dispersity(dispersity, ratio)
    rng = rng if rng is not None else np.random.default_rng()
    a, b = (0, n) if comm is None else row_block(n, comm)
    diam, species = diameter_rows(a, b, n, dispersity, ratio, rng)
    volume = exactsum.total(comm, sphere_volume(diam, d), a, n)
    L = float((volume / phi) ** (1.0 / d))
    pos = position_rows(a, b, n, d, L, dispersity, rng)
    rng.bit_generator.advance(diameter_draws(n, dispersity) + n * d)
    dmax = float(diam.max()) if len(diam) else 0.0
    if comm is not None:
        dmax = as_mpi(comm).allreduce(dmax, op=max_op())
    x, rows = spatial_rows(comm, a, pos, {"diam": diam, "species": species}, L, dmax, n)
    # the Jammer's phi: its sphere volume summed in the new order (a bi sum differs at round-off)
    phi_start = float(exactsum.total(comm, sphere_volume(rows["diam"], d), a, n) / L**d)
    return StateRows(comm, n, L, alpha, eps, phi_start, a, x, rows["diam"],
                     {"species": rows["species"]}, frozenset({"species"}))


def random_packing(d, n, phi, alpha=DEFAULT_ALPHA, dispersity="mono", ratio=DEFAULT_RATIO,
                   rng=None):
    """Uniform random positions at volume fraction phi: an infinite-temperature configuration
    (the whole of it: ``start_rows`` on one rank)."""
    rows = start_rows(None, d, n, phi, alpha, dispersity, ratio, rng)
    return Packing(rows.x, rows.diam, rows.L, alpha, meta=dict(rows.meta))
