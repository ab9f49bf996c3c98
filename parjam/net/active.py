"""The one distributed active network of a packing: the contacts and non-rattlers that every
analysis (hessian, spectrum, kpm, moduli, analyze) builds on, with O(N/P) memory per rank.

Built on parjam.net.domain's slabs:

1. ``SlabDomain.balanced`` + ``migrate``: each rank owns the particles of its slab, whatever
   rows it started with (e.g. its row range of the packing file);
2. one ghost exchange (``halo`` of width max sigma) and ``neighbour_pairs``: the contacts of the
   owned particles, r_ij < sigma_ij = (s_i + s_j)/2, as *half-edges* (i owned, j owned or ghost),
   so every contact appears exactly twice over all ranks, once on the owner of each end.  The
   separation is the serial one (``system.pair_separation`` of the wrapped positions), so the
   geometry is bit-identical to ``network.analyze``;
3. rattlers (fewer than d + 1 contacts) removed iteratively as in ``network.find_rattlers``: each
   sweep counts the owned particles' live contacts, the ghosts' "alive" flags refreshed by one
   ``halo.pull``, and one allreduce of the removed count stops the loop;
4. the parallel re-index: the non-rattlers are numbered 0..N'-1 rank by rank (an exclusive
   scan of the owned active counts), so each rank's owned active particles are the contiguous
   block rows [lo, hi) of every operator; the ghosts' numbers come by one pull.  This numbering
   is *not* the serial one (sorted by particle id) unless P = 1; ``ids`` maps it back.

The same machinery serves sub-networks (the l* cubes of parjam.lengths.whole): ``prune`` is the
iterative removal at any threshold from any starting set, ``components`` the connected pieces by
min-label propagation, ``number_halo`` the ghost plan of the active numbering (the half-edges'
other ends), on which ``renumber`` re-indexes the survivors.

The owned particles' wrapped positions stay on the network (``pos``, ``active_pos`` for the
active rows) for the analyses that need a row's position (softmodes' cuts and f(x)).

Global numbers (N', Nc, Nc_iso, pressure, stress, energy, forces) are allreduced sums of the
half-edges (each contact counted with weight 1/2); nothing of length N or Nc is gathered.
Conventions and the paper's definitions are parjam.net.network's (module doc there).
"""

from dataclasses import dataclass

import numpy as np

from parjam import env
from parjam.errors import ParjamError
from parjam.net import potential
from parjam.net.blocks import contact_blocks
from parjam.net.domain import Halo, SlabDomain, as_mpi, send_rows
from parjam.net.network import Contacts, NetworkNumbers
from parjam.net.system import DUPLICATE_TOL, pair_separation, sphere_volume


@dataclass
class ActiveNetwork(NetworkNumbers):
    """This rank's share of the contact network (see the module doc); N', Nc, z, dz, ... and
    ``summary`` as network.Network's."""

    comm: object  # mpi4py communicator
    d: int
    n: int  # N, all particles
    n_active: int  # N', non-rattlers (global)
    n_contacts: int  # Nc among non-rattlers (global)
    lo: int  # owned active rows [lo, hi)
    hi: int
    L: np.ndarray  # box edges
    alpha: float
    eps: float
    phi: float
    ids: np.ndarray  # global particle ids of the owned active rows lo..hi-1
    owned_ids: np.ndarray  # global ids of every owned particle (rattlers too)
    rattler: np.ndarray  # owned particles: rattler flag
    contacts: Contacts  # half-edges among non-rattlers, global active numbers
    n_all_contacts: int  # every contact, rattlers' too (global)
    energy: float
    stress: np.ndarray  # (1/V) sum_contacts -V'(r) r_a r_b / r (compressive positive)
    max_force: float
    mean_force: float
    pos: np.ndarray = None  # wrapped positions of every owned particle (rows of owned_ids)

    @property
    def volume(self):
        return float(np.prod(self.L))

    @property
    def rows(self):
        """The owned active row range (block rows of the operators)."""
        return self.lo, self.hi

    @property
    def n_local(self):
        return self.hi - self.lo

    @property
    def dof(self):
        return self.n_active * self.d

    @property
    def n_rattlers(self):
        return self.n - self.n_active

    @property
    def active_pos(self):
        """Wrapped positions of the owned active rows lo..hi-1 (particles ``ids``)."""
        return self.pos[~self.rattler]

    @property
    def pressure(self):
        return float(np.trace(self.stress) / self.d)

    def blocks(self, kind="full"):
        """Per-half-edge blocks K_ij of Eq. (1) (parjam.vib.hessian)."""
        c = self.contacts
        return contact_blocks(c.rij, c.r, c.sigma, self.alpha, self.eps, kind)


def half_edges(dom, x, diam, ids, cutoff):
    """Every contact of the owned particles as half-edges (rows of [owned; ghosts]), sorted by
    (owned row, id of the other end), the halo plan and the ghosts' global ids."""
    halo = dom.halo(x, ids, cutoff)
    n_own = len(x)
    pts = np.concatenate([x, halo.pull(x)])  # wrapped positions: the serial separation
    dia = np.concatenate([diam, halo.pull(diam)])
    gid = np.concatenate([ids, halo.ids])
    pairs = dom.neighbour_pairs(x, halo, cutoff)
    a, b = pairs[:, 0], pairs[:, 1]
    rij = pair_separation(pts[a], pts[b], dom.L)
    r = np.sqrt(np.einsum("ij,ij->i", rij, rij))
    sigma = 0.5 * (dia[a] + dia[b])
    c = r < sigma
    a, b, rij, r, sigma = a[c], b[c], rij[c], r[c], sigma[c]
    both = b < n_own  # owned-owned: found once, stored from both ends
    hi = np.concatenate([a, b[both]])
    hj = np.concatenate([b, a[both]])
    rij = np.concatenate([rij, -rij[both]])
    r, sigma = np.concatenate([r, r[both]]), np.concatenate([sigma, sigma[both]])
    order = np.lexsort((gid[hj], hi))
    return Contacts(hi[order], hj[order], rij[order], r[order], sigma[order]), halo, gid


def remove_rattlers(comm, halo, n_own, d, edges):
    """Owned rattler mask: fewer than d + 1 live contacts, removed iteratively (each sweep one
    pull of the ghosts' flags and one allreduce)."""
    return ~prune(comm, halo, n_own, edges, d + 1)[0]


def prune(comm, halo, n_own, edges, min_contacts, alive=None):
    """Iteratively remove the owned rows with fewer than ``min_contacts`` live contacts among
    ``edges`` (half-edges, i owned, rows of [owned; ghosts of ``halo``]), starting from the owned
    ``alive`` mask (all by default; the ghosts' flags come from their owners).  Every sweep
    removes all the rows below the threshold at once (one pull of the ghosts' flags, one
    allreduce of the removed count), as ``network.find_rattlers`` and
    ``lengths.cubes.prune_underconstrained`` do serially.  Returns (alive, this rank's
    sum of min_contacts - z_i over the rows it removed, z_i their live contacts then)."""
    alive = np.ones(n_own, dtype=bool) if alive is None else np.array(alive, dtype=bool)
    deficit = 0
    while True:
        flag = np.concatenate([alive, halo.pull(alive)])
        live = flag[edges.i] & flag[edges.j]
        deg = np.bincount(edges.i[live], minlength=n_own)
        new = alive & (deg < min_contacts)
        if comm.allreduce(int(new.sum())) == 0:
            return alive, deficit
        deficit += int((min_contacts - deg[new]).sum())
        alive &= ~new


def components(comm, halo, n_own, edges, alive, first):
    """Connected pieces of the live rows (owned ``alive`` mask; ``edges`` half-edges, i owned,
    rows of [owned; ghosts of ``halo``], both ends alive) by min-label propagation: every row
    starts with its global number (``first`` + owned row), each sweep pulls the ghosts' labels
    and gives every piece of this rank's graph of owned and ghost rows (scipy) the smallest
    label in it; one allreduce of the changed rows per sweep stops the loop (sweeps ~ the
    number of times a piece crosses between ranks, not its diameter).  Returns (labels of the
    owned rows, the smallest number of each row's piece; -1 for dead rows, number of pieces)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    big = np.iinfo(np.int64).max
    label = np.where(alive, first + np.arange(n_own, dtype=np.int64), big)
    n_rows = n_own + halo.n
    graph = sp.coo_matrix((np.ones(len(edges.i)), (edges.i, edges.j)), shape=(n_rows, n_rows))
    _, piece = connected_components(graph, directed=False)
    while True:
        rows = np.concatenate([label, halo.pull(label)])
        low = np.full(piece.max() + 1 if n_rows else 0, big, dtype=np.int64)
        np.minimum.at(low, piece, rows)
        new = np.where(alive, low[piece[:n_own]], big)
        changed = int(np.sum(new != label))
        label = new
        if comm.allreduce(changed) == 0:
            break
    roots = int(np.sum(alive & (label == first + np.arange(n_own))))
    return np.where(alive, label, -1), comm.allreduce(roots)


def number_halo(comm, lo, hi, wanted):
    """The ghost plan of the active numbering: a parjam.net.domain.Halo whose ``pull`` takes values
    of the owned active rows [lo, hi) and returns those of every distinct number of ``wanted``
    outside [lo, hi) (the other ends of the half-edges), in ascending order (``ids``).  The
    owner of a number is the rank whose [lo, hi) holds it (an allgather of the P row ranges);
    one exchange of the requests (collective)."""
    comm = as_mpi(comm)
    wanted = np.unique(np.asarray(wanted, dtype=np.int64))
    ghosts = wanted[(wanted < lo) | (wanted >= hi)]
    ends = np.array(comm.allgather(int(hi)), dtype=np.int64)
    owner = np.searchsorted(ends, ghosts, side="right")
    nums, got = send_rows(comm, owner, ghosts, {"src": np.full(len(ghosts), comm.Get_rank())})
    order = np.lexsort((nums, got["src"]))
    size = comm.Get_size()
    send_counts = np.bincount(got["src"], minlength=size).astype(np.int64)
    recv_counts = np.bincount(owner, minlength=size).astype(np.int64)
    return Halo(comm, nums[order] - lo, send_counts, recv_counts, np.arange(len(ghosts)),
                ghosts, np.zeros((len(ghosts), 1)))


def halo_rows(lo, hi, halo, numbers):
    """Rows of [owned active rows lo..hi-1; ghosts of ``number_halo``] of active ``numbers``
    (each owned or a ghost)."""
    numbers = np.asarray(numbers, dtype=np.int64)
    own = (numbers >= lo) & (numbers < hi)
    return np.where(own, numbers - lo, (hi - lo) + np.searchsorted(halo.ids, numbers))


def renumber(comm, halo, alive):
    """Global active numbers of the owned rows (-1 for rattlers) and of the ghosts: the owned
    non-rattlers of rank r are lo_r .. hi_r - 1, lo_r the exclusive scan of the counts."""
    n_loc = int(alive.sum())
    hi = comm.scan(n_loc)
    lo = hi - n_loc
    number = np.full(len(alive), -1, dtype=np.int64)
    number[alive] = lo + np.arange(n_loc)
    return np.concatenate([number, halo.pull(number)]), lo, hi


def check_distinct(comm, edges, ids, gid, diam, tol):
    """ValueError on every rank if two centres are closer than ``tol`` x the smallest diameter
    (they would divide every force by r = 0), naming the first pair (collective)."""
    dmin = comm.allreduce(float(diam.min()) if len(diam) else np.inf, op=min_op())
    close = np.flatnonzero(edges.r < tol * dmin)
    pair = sorted((int(ids[edges.i[close[0]]]), int(gid[edges.j[close[0]]]))) if len(close) \
        else None
    pairs = [p for p in comm.allgather(pair) if p]
    if pairs:
        raise ValueError(f"particles {pairs[0][0]} and {pairs[0][1]} coincide")


def build(comm, x, diam, ids, L, alpha=2.0, eps=1.0, coincide=1e-9):
    """The distributed active network from any distribution of the particles over the ranks
    (rows ``x``, ``diam`` with global ``ids``; collective).  ``L`` is the box edge (scalar) or
    edges; centres closer than ``coincide`` x the smallest diameter are refused (ValueError)."""
    comm = as_mpi(comm)
    x = np.asarray(x, dtype=np.float64)
    d = x.shape[1]
    dom = SlabDomain.balanced(comm, L, x)
    x, ids, f = dom.migrate(x, ids, {"diam": np.asarray(diam, dtype=np.float64)})
    diam = f["diam"]
    n = comm.allreduce(len(ids))
    dmax = comm.allreduce(float(diam.max()) if len(diam) else 0.0, op=max_op())
    if not 2.0 * dmax < dom.L.min():
        raise ValueError(f"box edge {dom.L.min():.3g} is not larger than twice the neighbour "
                         f"cutoff {dmax:.3g}: too few particles for this box")
    allc, halo, gid = half_edges(dom, x, diam, ids, dmax * (1.0 + 1e-9))
    check_distinct(comm, allc, ids, gid, diam, coincide)
    rattler = remove_rattlers(comm, halo, len(x), d, allc)
    number, lo, hi = renumber(comm, halo, ~rattler)
    keep = (number[allc.i] >= 0) & (number[allc.j] >= 0)
    act = allc.subset(keep)
    act = Contacts(number[act.i], number[act.j], act.rij, act.r, act.sigma)
    sums = network_sums(comm, allc, act, x, diam, rattler, alpha, eps, float(np.prod(dom.L)))
    return ActiveNetwork(
        comm=comm, d=d, n=n, n_active=comm.allreduce(hi - lo), n_contacts=sums["nc"], lo=lo,
        hi=hi, L=dom.L, alpha=float(alpha), eps=float(eps), phi=sums["phi"], ids=ids[~rattler],
        owned_ids=ids, rattler=rattler, contacts=act, n_all_contacts=sums["n_all"],
        energy=sums["energy"], stress=sums["stress"], max_force=sums["max_force"],
        mean_force=sums["mean_force"], pos=x)


def network_sums(comm, allc, act, x, diam, rattler, alpha, eps, volume):
    """The global numbers of network.analyze from this rank's half-edges (each contact counted
    with weight 1/2) and owned particles, by allreduce: Nc, phi, energy, stress
    sigma_ab = -(1/V) sum V'(r) r_a r_b / r, the largest residual force on a non-rattler and the
    mean contact force."""
    d = x.shape[1]
    dv = potential.dV(allc.r, allc.sigma, alpha, eps)
    stress = 0.5 * np.einsum("k,ka,kb->ab", -(dv / allc.r), allc.rij, allc.rij) / volume
    force = np.zeros_like(x)  # on each owned particle, from all its contacts
    for a in range(d):
        force[:, a] = np.bincount(allc.i, weights=(dv / allc.r) * allc.rij[:, a],
                                  minlength=len(x))
    fnorm = np.sqrt(np.einsum("ij,ij->i", force, force))[~rattler]
    fmag = np.abs(potential.dV(act.r, act.sigma, alpha, eps))
    sums = comm.allreduce(np.array([
        len(act), len(allc), 0.5 * potential.energy(allc.r, allc.sigma, alpha, eps).sum(),
        0.5 * fmag.sum(), sphere_volume(diam, d).sum()]))
    nc = int(round(sums[0])) // 2
    return {"nc": nc, "n_all": int(round(sums[1])) // 2, "energy": float(sums[2]),
            "stress": comm.allreduce(stress), "phi": float(sums[4] / volume),
            "max_force": comm.allreduce(float(fnorm.max()) if len(fnorm) else 0.0, op=max_op()),
            "mean_force": float(sums[3] / nc) if nc else 0.0}


def max_op():
    from mpi4py import MPI
    return MPI.MAX


def min_op():
    from mpi4py import MPI
    return MPI.MIN


def row_block(n, comm):
    """This rank's contiguous block of n rows (the same split as PETSc's): (start, stop)."""
    comm = as_mpi(comm)
    size, rank = comm.Get_size(), comm.Get_rank()
    base, extra = divmod(n, size)
    start = rank * base + min(rank, extra)
    return start, start + base + (1 if rank < extra else 0)


def from_packing(comm, pack):
    """The distributed network of a packing every rank holds (tests and small systems): each
    rank starts from its row block, as if it had read only that."""
    start, stop = row_block(pack.n, comm)
    return build(comm, pack.pos[start:stop], pack.diam[start:stop],
                 np.arange(start, stop, dtype=np.int64), pack.L, pack.alpha, pack.eps)


def from_rows(comm, rows):
    """The distributed active network of a packing's rows (collective): ``rows`` holds this
    rank's ``pos``, ``diam`` and ``ids`` with the packing's ``L``, ``alpha``, ``eps`` (a packing
    file's row block, parjam.files.rowio.read_rows).  Coinciding centres (system.DUPLICATE_TOL)
    are one ParjamError naming ``rows.path``, raised on every rank."""
    try:
        with network_event():
            return build(comm, rows.pos, rows.diam, rows.ids, rows.L, rows.alpha, rows.eps,
                         coincide=DUPLICATE_TOL)
    except ValueError as exc:  # raised on every rank alike (check_distinct)
        raise ParjamError(f"{getattr(rows, 'path', 'packing')}: {exc}") from None


NETWORK_EVENT = "parjam: active network"
_event = []


def network_event():
    """The PETSc log event around building the network: ``-log_view`` shows it."""
    if not _event:
        _event.append(env.petsc().Log.Event(NETWORK_EVENT))
    return _event[0]


def home_rows(comm, n, ids, values=None):
    """Rows keyed by particle ids (any order, any rank) moved to the rank whose contiguous id
    block (``row_block(n)``) holds them, sorted by id there (collective, all-to-all of these
    rows only).  Returns (ids, values) of this rank's home rows; ``values`` (rows along axis 0)
    may be None.  Concatenated over the ranks in rank order they are in id order: the order of
    a file's rows."""
    comm = as_mpi(comm)
    ids = np.asarray(ids, dtype=np.int64)
    size = comm.Get_size()
    base, extra = divmod(n, size)  # row_block's split: the first `extra` blocks are longer
    starts = np.array([r * base + min(r, extra) for r in range(size + 1)], dtype=np.int64)
    home = np.searchsorted(starts, ids, side="right") - 1
    order = np.argsort(home, kind="stable")
    bounds = np.searchsorted(home[order], np.arange(size + 1))
    send_ids = [ids[order[bounds[r]:bounds[r + 1]]] for r in range(size)]
    got_ids = np.concatenate(comm.alltoall(send_ids)) if size > 1 else send_ids[0]
    got = None
    if values is not None:
        values = np.asarray(values)
        send = [values[order[bounds[r]:bounds[r + 1]]] for r in range(size)]
        got = np.concatenate(comm.alltoall(send)) if size > 1 else send[0]
    sort = np.argsort(got_ids, kind="stable")
    return got_ids[sort], (None if got is None else got[sort])
