"""The packing engine on the spatial domain decomposition (parjam.net.domain): FIRE's state of one
packing held as numpy arrays of each rank's own particles (a slab) and a halo of ghosts, so that
no rank holds or loops over all N particles.

Each rank owns the particles of its slab (positions, velocities, diameters, global ids, sorted
by id).  A ghost plan hands the particles that left a slab, and only those, to their new
owner (one exchange, none when no particle left any slab; the slab bounds move to the count
quantiles of the ranks' shares again, before the hand-over, when the counts would drift by more
than REBALANCE or the measured work asks for other shares: BALANCE_EVERY), plans the ghosts
within cutoff + margin of the slab (cutoff = max diameter + skin, margin = HALO_MARGIN skins;
``SlabDomain.halo``: their positions, velocities and diameters pulled in one exchange) and lists
the pairs of owned particles and ghosts in compiled code (``cellsearch.slab_pairs``; on one
rank, where all ghosts are periodic images, the fully periodic cell search
``cellsearch.cell_pair_lists``, with no halo).  A pair is listed when it is within its own
reach, (d_i + d_j) / 2 + skin (the cells' edge is the largest reach, max diameter + skin): a
third fewer pairs in a 1 : 1.4 mixture than one cutoff for all.  The neighbour rebuilds after
a plan, while the displacements since it (summed over the lists, a bound every rank computes
alike) stay within half the margin, search the same owned rows and ghosts again at their
current positions, with no exchange at all (``rebuild``).
Both searches visit each pair of neighbouring cells once (a half stencil) and sort the pairs
into the global (i, j) order afterwards.

A FIRE step on P ranks has ONE synchronisation (two on the steps where a bound cannot tell
that the neighbour lists still hold: see ``step``): the compiled update moves the owned particles
AND the ghosts (each rank holds its ghosts' positions, velocities and forces, and moves them
with the same arithmetic as their owners: the same bits), the compiled forces and partial sums
of the owned particles follow at once -- no halo wait -- and then the forces of the particles
that are other ranks' ghosts are sent to them (non-blocking, point to point) while the step's
sums are reduced (MPI's own integer sum, then maximum, back to back); the ghosts' forces are in
place when they return.  So the halo traffic is hidden behind the reduction the step needs
anyway.

Ghost pairs are computed on both sides: a pair of particles on two ranks is listed by both, and
each adds the force to its own particle only (no second exchange to push ghost forces back).
The pairs are listed in global (i, j) order and the separation is the minimum image of the
difference of the continuous (never re-wrapped) positions, exactly as the serial kernel does,
so the force on a particle is bitwise independent of the number of ranks and of when the list
was rebuilt.  The sums over particles (energy, F.v, |F|^2, |v|^2) are exact (fixed-point
accumulators, parjam.net.exactsum, reduced as integers and rounded once) and the maxima are
exact anyway: they too are the same bits on any number of ranks and for any decomposition, so
FIRE's trajectory is.

The positions are kept unwrapped between rebuilds (a particle's coordinates change only by
FIRE's updates): the wrapped copy a rebuild needs for ownership and search is temporary.
"""

import contextlib
import time

import numpy as np

from parjam.pack import cellsearch, kernels, rowops
from parjam.net.domain import SlabDomain, as_mpi, send_rows
from parjam.logevents import ALLREDUCE, FORCE, HALO, MIGRATE, REBUILD, SEARCH, event

# new slab bounds when the most loaded rank would hold 2 % more than the mean after a rebuild
# (a rebuild's hand-over moves the particles anyway; new bounds cost one histogram allreduce)
REBALANCE = 1.02
TAG = 7103  # the point-to-point messages of the ghosts' forces
# the ghost plan reaches HALO_MARGIN skins beyond the lists' cutoff, so that the rebuilds after
# it, while no particle can have moved half that margin since the plan, search the same owned
# rows and ghosts again: no hand-over, no halo exchange, no collective (``rebuild``)
HALO_MARGIN = 2.2
# load balance by measured work: every BALANCE_EVERY steps (0: never) the ranks compare the time
# their force kernels and searches took with the work they did (one allgather of two numbers);
# when the busiest took over BALANCE_TOL times the mean, the next ghost plan moves the slab bounds
# so that each rank holds a share of the particles proportional to its measured speed (a slower
# or busier core, a denser slab).  Shorter intervals follow a core that slows down for seconds
# more closely, but the hand-overs they cause cost what they save (docs/results/pack-ranks.md,
# "Tried and not kept").  The files do not depend on it: only the decomposition changes.
BALANCE_EVERY = 200
BALANCE_TOL = 1.02


class FireSums:
    """The global sums of one fused FIRE step (kernels.fire_sums of the reduced buffer); the
    energy is NaN when the step was not asked for it."""

    __slots__ = ("energy", "power", "f2", "v2", "fmax", "vmax", "disp")

    def __init__(self, s, energy=True):
        self.energy, self.power = float(s[0]) if energy else float("nan"), float(s[1])
        self.f2, self.v2 = float(s[2]), float(s[3])
        self.fmax, self.vmax, self.disp = (float(np.sqrt(s[4])), float(np.sqrt(s[5])),
                                           float(np.sqrt(s[6])))


class SlabEngine:
    """Forces and the fused FIRE step of one packing (cubic box of edge L, d dimensions) whose
    particles are spread over the slabs of communicator ``comm``.  ``x``, ``ids``, ``diam`` and
    ``v`` are the rows this rank brings (any split of the N particles: every rank's rows are
    handed to their slabs here)."""

    def __init__(self, comm, L, alpha, eps, skin, x, ids, diam, v=None):
        self.comm = as_mpi(comm)
        self.rank, self.size = self.comm.Get_rank(), self.comm.Get_size()
        x = np.array(x, dtype=np.float64)  # copies: the engine moves its own
        self.d = x.shape[1]
        self.L = float(L)
        self.alpha, self.eps, self.skin = alpha, eps, float(skin)
        # the largest and (negated) the smallest diameter of all ranks
        ext = np.array([np.max(diam), -np.min(diam)] if len(diam) else [0.0, -np.inf])
        self.comm.Allreduce(_mpi_in_place(), ext, op=_mpi_max())
        self.cut = float(ext[0]) + self.skin
        # a mixture lists each pair within its own reach (d_i + d_j) / 2 + skin (a third fewer
        # pairs at 1 : 1.4); equal spheres within the cutoff (the same pairs, a cheaper search)
        self.mixture = bool(-ext[1] < ext[0])
        self.n_rebuilds = self.n_migrated = 0
        self.n_plans = 0  # the rebuilds that handed particles over and planned the ghosts anew
        # the ghosts reach self.cut + self.margin (below half the box, as SlabDomain.halo
        # wants); self.drift bounds any particle's displacement since the ghost plan
        self.margin = (max(0.0, min(HALO_MARGIN * self.skin, 0.49 * self.L - self.cut))
                       if self.size > 1 else 0.0)
        self.drift = 0.0
        self.search = None  # what a search-only rebuild needs (``_plan``)
        # each rank's share of the particles (None: equal), the seconds of kernel and search
        # work since the last comparison and the owned particles summed over its steps (the work
        # done: the slabs may have changed in between), and whether the next rebuild must plan
        # anew for it
        self.shares, self.busy, self.work, self.n_steps, self.replan = None, 0.0, 0, 0, False
        self.n_balances = 0  # the comparisons that changed the shares
        self.n_checks = 0  # the steps whose list the bound could not keep, decided by _disp2
        self.acc = np.zeros(kernels.FIRE_ACC, dtype=np.int64)  # the step's sums (exact)
        # its exact accumulators (summed over the ranks as integers) and its last three
        # entries, maxima of non-negative doubles as their bits (which order as the values)
        self.sums_part, self.max_part = self.acc[:-3], self.acc[-3:]
        self.sums = np.zeros(kernels.N_SUMS)
        self.scratch = cellsearch.Scratch()  # the searches' work arrays, kept between rebuilds
        v = np.zeros_like(x) if v is None else np.array(v, dtype=np.float64)
        self.domain = SlabDomain.balanced(self.comm, self.L, x)
        ids = np.asarray(ids, dtype=np.int64)
        o = np.argsort(ids, kind="stable")  # rows sorted by id (migrate sorts them too)
        self._own(x[o], ids[o], np.asarray(diam, dtype=np.float64)[o], v[o])
        self.rebuild()

    # --- the decomposition ---------------------------------------------------------------------
    def _own(self, x, ids, diam, v):
        self.xu, self.ids, self.diam, self.v = x, ids, diam, v

    def rebuild(self, rebalance=False, moved=None):
        """Migration (to new bounds if the counts would drift or ``rebalance``), the ghost plan
        and the pair list at the current positions (collective).

        ``moved``: the largest displacement of any particle since the last list (the value every
        rank reduced alike, so all ranks decide alike).  While the sum of those since the ghost
        plan stays within half of ``margin`` (HALO_MARGIN skins), no particle can have left the
        slab it was owned in by more than that, nor can a particle within the cutoff of an owned
        one be outside the plan's halo (cutoff + margin): the same owned rows and ghosts are
        searched again at their current positions (``_search``) -- no hand-over, no exchange.
        The forces do not depend on which rebuild this is: only touching pairs exert forces, each
        particle's summed in the global (i, j) order."""
        if moved is not None and self.search is not None and not self.replan:
            drift = (self.drift + moved) * (1.0 + 1e-12)  # the triangle inequality, rounded up
            if drift <= 0.5 * self.margin:
                with event(REBUILD):
                    self.drift = drift
                    self._search()
                    self.n_rebuilds += 1
                return
        self.drift = 0.0
        self.n_plans += 1
        with event(REBUILD):
            # folded positions (and owners), as self.domain.fold and .owner give them
            xw, dest = rowops.fold_owner(self.xu, self.L,
                                          self.domain.bounds if self.size > 1 else None)
            if self.size > 1:
                with event(MIGRATE):
                    # the rows each rank would own, and how many leave their slab in all
                    counts = np.bincount(dest, minlength=self.size + 1).astype(np.int64)
                    counts[-1] = np.count_nonzero(dest != self.rank)
                    self.comm.Allreduce(_mpi_in_place(), counts, op=_mpi_sum())
                    share = (np.full(self.size, 1.0 / self.size) if self.shares is None
                             else self.shares)
                    drifted = np.any(counts[:-1] > REBALANCE * share * counts[:-1].sum())
                    if rebalance or self.replan or drifted:
                        self.replan = False
                        self.domain = SlabDomain.balanced(self.comm, self.L, self.xu,
                                                          self.shares)
                        dest = rowops.fold_owner(xw, self.L, self.domain.bounds,
                                                  folded=True)[1]
                        counts[-1] = 1  # every rank hands over
                    if counts[-1]:  # else nothing moves: no exchange
                        xw = self._migrate(xw, dest)
            self._plan(xw)
            self.n_rebuilds += 1

    def _migrate(self, xw, dest):
        """The rows leaving this slab to their owners ``dest`` (one exchange of the leavers
        alone: ids, positions, velocities and diameters side by side), the arrivals merged in
        by id (both runs are sorted); returns the wrapped positions of the new rows."""
        leave = dest != self.rank
        out = np.flatnonzero(leave)
        self.n_migrated += len(out)
        ids_in, got = send_rows(self.comm, dest[out], self.ids[out],
                                {"x": self.xu[out], "v": self.v[out], "diam": self.diam[out]})
        if not len(out) and not len(ids_in):
            return xw
        keep = np.flatnonzero(~leave)
        n_new = len(keep) + len(ids_in)
        at = np.searchsorted(self.ids[keep], ids_in) + np.arange(len(ids_in))  # arrivals' rows
        rows = np.empty(n_new, dtype=np.int64)  # the new rows in [old rows; arrivals]
        rows[at] = len(self.ids) + np.arange(len(ids_in))
        mine = np.ones(n_new, dtype=bool)
        mine[at] = False
        rows[mine] = keep

        def merged(values, arrived):  # this rank's remaining rows and the arrivals, by id
            return rowops.merge_rows(rows, values, arrived)

        self._own(merged(self.xu, got["x"]), merged(self.ids, ids_in),
                  merged(self.diam, got["diam"]), merged(self.v, got["v"]))
        return merged(xw, rowops.fold_owner(got["x"], self.L)[0])

    def _plan(self, xw):
        """Ghosts, the force arrays and the pair list for the owned rows, whose wrapped
        positions are ``xw`` (collective)."""
        n_own = len(self.ids)
        # the last list's arrays go first (a rebuild's peak memory), its length sizes the next
        cap = int(1.25 * len(self.pi)) + 1024 if getattr(self, "pi", None) is not None else None
        self.kernel = self.pi = self.pj = self.f = self.ref = self.pdiam = self.search = None
        if self.size == 1 and self._plan_periodic(xw, cap):
            return
        # the ghost plan, and the ghosts' positions, velocities and diameters, in one exchange
        with event(HALO) if self.size > 1 else contextlib.nullcontext():  # one rank: a copy
            halo = self.domain.halo(xw, self.ids, self.cut + self.margin,
                                    [self.xu, self.v, self.diam])
        src = np.repeat(np.arange(self.size), halo.recv_counts)[halo.order]
        image = src == self.rank  # own particles seen across the periodic boundary
        foreign = np.flatnonzero(~image)
        row = np.empty(halo.n, dtype=np.int64)
        row[foreign] = n_own + np.arange(len(foreign))
        row[image] = np.searchsorted(self.ids, halo.ids[image])
        kinds = np.concatenate([np.zeros(n_own, dtype=np.int64), np.where(image, 1, 2)])
        gid = np.concatenate([self.ids, halo.ids])
        # the owned rows (sorted by id) and the other ranks' ghosts (by (id, shift)) merged by
        # id: a ghost goes after the owned ids below it and the ghosts before it
        low = np.empty(n_own + len(foreign), dtype=np.int64)
        at = np.searchsorted(self.ids, halo.ids[foreign]) + np.arange(len(foreign))
        mine = np.ones(len(low), dtype=bool)
        mine[at] = False
        low[at] = n_own + foreign
        low[mine] = np.arange(n_own)
        pts = np.concatenate([xw, halo.x])  # the search's points: owned rows, then the halo
        # their diameters, for the pairs' own reach (None: equal spheres, the cutoff)
        reach = np.concatenate([self.diam, halo.values[2]]) if self.mixture else None
        src = np.concatenate([np.arange(n_own), row])  # their rows of the kernel's arrays
        # the layers of cells aligned to the slab widened by what the owned rows may drift
        # before the next plan and the margin (the ghosts beyond it in layers of their own)
        slab = self.domain.bounds[self.rank:self.rank + 2] + np.array([-1.5, 1.5]) * self.margin
        t = time.perf_counter()
        with event(SEARCH):
            self.pi, self.pj = cellsearch.slab_pairs(pts, self.L, self.cut, src, gid, kinds,
                                                     low, cap, self.scratch, slab=slab,
                                                     diam=reach, skin=self.skin)
        self.busy += time.perf_counter() - t
        self._ghost_plan(halo, foreign)
        self._arrays(*(a[foreign] for a in halo.values), halo.ids[foreign])
        if self.margin > 0:
            # a point's search position is its row's (continuous) position plus this offset
            pts -= self.pos.take(src, axis=0)
            self.search = (src, pts, gid, kinds, low, slab, reach)

    def _search(self):
        """A rebuild of the pair list alone: the plan's points (owned rows, ghosts and images,
        which every rank moves alike) searched at their current positions, open along axis 0 as
        the plan placed them and folded into [0, L) along the others."""
        src, offset, gid, kinds, low, slab, reach = self.search
        cap = int(1.25 * len(self.pi)) + 1024
        self.kernel = self.pi = self.pj = None
        t = time.perf_counter()
        pts = rowops.search_points(src, self.pos, offset, self.L, ref=self.ref)  # ref = xu
        with event(SEARCH):
            self.pi, self.pj = cellsearch.slab_pairs(pts, self.L, self.cut, src, gid, kinds,
                                                     low, cap, self.scratch, slab=slab,
                                                     diam=reach, skin=self.skin)
        self.busy += time.perf_counter() - t
        del pts
        self.acc[-1] = 0
        self.kernel = kernels.FireKernel(self.pos, self.v_all, self.f_all, self.ref, self.pi,
                                         self.pj, self.pos, self.pdiam, self.acc, nown=self.n_own)

    def _ghost_plan(self, halo, foreign):
        """The per-step exchange of the ghosts' forces: the owned rows other ranks hold as
        ghosts, packed by destination (``send_index``), the received rows' places among this
        rank's ghost rows (``unpack``), and the (rank, first, last) slices of both buffers."""
        d = self.d
        self.send_index = np.ascontiguousarray(halo.send_index, dtype=np.int64)
        self.unpack = np.ascontiguousarray(halo.order[foreign], dtype=np.int64)
        self.sendbuf = np.empty((len(self.send_index), d))
        self.recvbuf = np.empty((int(np.sum(halo.recv_counts)), d))

        def slices(counts):
            ends = np.cumsum(counts)
            return [(r, int(e - c), int(e)) for r, (c, e) in enumerate(zip(counts, ends)) if c]

        # the buffers' parts, one per rank, as views made once (not sliced every step)
        self.send_parts = [(r, self.sendbuf[a:b]) for r, a, b in slices(halo.send_counts)]
        self.recv_parts = [(r, self.recvbuf[a:b]) for r, a, b in slices(halo.recv_counts)]

    def _plan_periodic(self, xw, cap):
        """One rank: every ghost is an image of an owned particle, so the fully periodic cell
        search (cellsearch.cell_pair_lists, the serial kernel's) lists the pairs, rows = ids
        (sorted), in (i, j) order, with no halo.  False when that search does not apply (fewer
        than 3 cells a side; no compiled library): the slab search serves then."""
        if not cellsearch.cell_search_applies(len(self.ids), self.d, self.L, self.cut):
            return False
        with event(SEARCH):
            got = cellsearch.cell_pair_lists(xw, self.L, self.cut, 0, len(self.ids), cap,
                                             self.scratch,
                                             diam=self.diam if self.mixture else None,
                                             skin=self.skin)
        self.pi, self.pj = got
        self.send_index = self.unpack = np.empty(0, dtype=np.int64)
        self.sendbuf = self.recvbuf = np.empty((0, self.d))
        self.send_parts = self.recv_parts = []
        self._arrays(np.empty((0, self.d)), np.empty((0, self.d)), np.empty(0))
        return True

    def _arrays(self, g_pos, g_v, g_diam, g_ids=None):
        """The arrays of the owned rows followed by the ghosts of other ranks -- positions,
        velocities, forces (the ghosts' arrive with the next exchange), diameters -- and the
        kernel bound to them."""
        n_own, n_all, d = len(self.ids), len(self.ids) + len(g_pos), self.d
        self.pos = np.empty((n_all, d))  # [owned; ghosts of other ranks]
        self.pos[:n_own], self.pos[n_own:] = self.xu, g_pos
        self.xu = self.pos[:n_own]  # the owned rows are views of the kernel's arrays
        self.v_all = np.empty((n_all, d))
        self.v_all[:n_own], self.v_all[n_own:] = self.v, g_v
        self.v = self.v_all[:n_own]
        self.f_all = np.zeros((n_all, d))
        self.f = self.f_all[:n_own]
        self.pdiam = np.concatenate([self.diam, g_diam])
        # the global id of each row (owned, then other ranks' ghosts): what the lists' rows are
        self.row_ids = self.ids if g_ids is None else np.concatenate([self.ids, g_ids])
        self.ref = self.xu.copy()
        self.acc[-1] = 0  # the displacement since the list was built (the update keeps it)
        # the per-step packing of the ghosts' forces to send, and the unpacking of those received
        self.pack_forces = rowops.RowGather(self.send_index, self.f, self.sendbuf)
        self.unpack_forces = rowops.RowGather(self.unpack, self.recvbuf, self.f_all[n_own:])
        self.kernel = kernels.FireKernel(self.pos, self.v_all, self.f_all, self.ref, self.pi,
                                         self.pj, self.pos, self.pdiam, self.acc, nown=n_own)

    @property
    def n_own(self):
        return len(self.ids)

    # --- forces and the fused FIRE step ---------------------------------------------------------
    def start(self, energy=True):
        """Forces at the current positions and the global FireSums (collective; the energy
        too unless ``energy`` is False).  Positions or velocities changed from outside (``xu``,
        ``v``) need a ``rebuild()`` first.  Called again at the same positions it gives the same
        forces and sums, bit for bit."""
        self._call(self._forces(energy), 0.0, False, 0.0, 1.0, 0.0)
        return self._exchange(energy)

    @staticmethod
    def _forces(energy):
        return kernels.FIRE_FORCES | (kernels.FIRE_ENERGY if energy else 0)

    def step(self, dt, reset, mix_v, mix_f, last, energy=True):
        """One FIRE step (see ``parjam_fire_step``): if ``reset`` step half back and zero v;
        v += dt F; v = mix_v v + mix_f F; x += dt v (owned particles and ghosts alike); then
        the forces at the new positions and the global FireSums (``_exchange``: one allreduce,
        the ghosts' forces alongside).  On one rank the kernel checks the displacement since the
        last rebuild itself; on several ranks the list is kept without a reduction when that
        displacement plus a bound on this step's (from ``last``, the previous sums) stays below
        half the skin, and else the largest displacement after the update, reduced, decides as
        on one rank: the same steps rebuild on any number of ranks.  ``energy`` False: the sums'
        energy is not computed (NaN; FIRE decides on the others)."""
        back = -0.5 * dt
        forces = self._forces(energy)
        if self.size == 1:
            stale = self._call(kernels.FIRE_UPDATE | forces, dt, reset, back,
                               mix_v, mix_f, stale2=(0.5 * self.skin) ** 2)
            if stale:
                self.rebuild()
                self._call(forces, dt, reset, back, mix_v, mix_f)
            return self._exchange(energy)
        self.n_steps += 1
        if BALANCE_EVERY and self.n_steps % BALANCE_EVERY == 0:
            self.weigh()
        vmax = 0.0 if reset else last.vmax
        bound = dt * (mix_v * (vmax + dt * last.fmax) + mix_f * last.fmax)
        if reset:
            bound += 0.5 * dt * last.vmax
        if (last.disp + bound) * (1.0 + 1e-6) < 0.5 * self.skin:  # the list holds: one call
            self._call(kernels.FIRE_UPDATE | forces, dt, reset, back, mix_v, mix_f)
        else:
            # the bound says it may not: the update, then the largest displacement of all
            # (one small reduction) decides as one rank's kernel does, so the lists are rebuilt
            # at the same steps on any number of ranks (the bound alone rebuilt 7 % more often)
            self._call(kernels.FIRE_UPDATE, dt, reset, back, mix_v, mix_f)
            disp2 = self._disp2()
            if disp2 >= (0.5 * self.skin) ** 2:
                self.rebuild(moved=float(np.sqrt(disp2)))
            self._call(forces, dt, reset, back, mix_v, mix_f)
        self.work += self.n_own
        return self._exchange(energy)

    def _disp2(self):
        """The largest displacement^2 of any particle since the lists were built (collective:
        the update's per-rank maxima, as the bits of non-negative doubles, reduced by MAX)."""
        from mpi4py import MPI

        with event(ALLREDUCE):
            self.n_checks += 1
            got = self.acc[-1:].copy()
            self.comm.Allreduce(MPI.IN_PLACE, got, op=MPI.MAX)
        return float(got.view(np.float64)[0])

    def _call(self, mode, dt, reset, back, mix_v, mix_f, stale2=0.0):
        with event(FORCE):
            t = time.perf_counter()
            got = self.kernel(mode, self.L, dt, reset, back, mix_v, mix_f, stale2, self.alpha,
                              self.eps, 0, self.n_own)
            self.busy += time.perf_counter() - t
            return got

    def weigh(self):
        """Compare the ranks' work since the last comparison (collective: an allgather of each
        rank's busy seconds and work, its owned particles summed over the steps since -- or its
        particles, if no step was taken); when the busiest rank took over BALANCE_TOL times
        the mean, the shares become proportional to each rank's work per busy second
        (within a factor 2 of equal ones), for the next rebuild to plan with.  Every rank
        decides on the same gathered numbers."""
        both = np.empty((self.size, 2))
        work = self.work if self.work > 0 else self.n_own
        self.comm.Allgather(np.array([self.busy, float(work)]), both)
        self.busy, self.work = 0.0, 0
        busy, n = both[:, 0], both[:, 1]
        if busy.min() <= 0.0 or n.min() <= 0.0 or busy.max() <= BALANCE_TOL * busy.mean():
            return
        speed = n / busy
        shares = np.clip(speed / speed.sum(), 0.5 / self.size, 2.0 / self.size)
        self.shares = shares / shares.sum()
        self.replan = True
        self.n_balances += 1

    def _exchange(self, energy):
        """The step's synchronisation (collective): the forces of the owned particles that
        other ranks hold as ghosts go to them (non-blocking, point to point) while the FIRE
        sums are reduced -- one allreduce of the kernel's buffer (integer sums of the exact
        accumulators, maxima of the rest), rounded to doubles once: the same bits on any
        number of ranks; then the ghosts' forces are unpacked into their rows."""
        if self.size > 1:
            from mpi4py import MPI

            comm = self.comm
            with event(HALO):
                self.pack_forces()
                reqs = [comm.Irecv(buf, source=r, tag=TAG) for r, buf in self.recv_parts]
                reqs += [comm.Isend(buf, dest=r, tag=TAG) for r, buf in self.send_parts]
            with event(ALLREDUCE):
                # MPI's own integer sum and maximum, in two calls: a Python op in one call cost
                # 14 - 40 us a step against 6 - 8 us (N = 1,024 - 16,384 on 2 ranks)
                comm.Allreduce(MPI.IN_PLACE, self.sums_part, op=MPI.SUM)
                comm.Allreduce(MPI.IN_PLACE, self.max_part, op=MPI.MAX)
            with event(HALO):
                MPI.Request.Waitall(reqs)
                self.unpack_forces()
        return FireSums(self.kernel.sums(self.sums), energy)

    # --- hand-over to row blocks (lazy gathers) ------------------------------------------------
    def to_blocks(self, ranges, values):
        """Per-particle ``values`` (n_own, ...) of this rank's rows sent to the contiguous id
        blocks ``ranges`` (P + 1 ids: PETSc's ownership), sorted by id (collective)."""
        dest = np.searchsorted(np.asarray(ranges), self.ids, side="right") - 1
        _, got = send_rows(self.comm, dest, self.ids, {"a": values})
        return got["a"]


def _mpi_max():
    from mpi4py import MPI

    return MPI.MAX


def _mpi_sum():
    from mpi4py import MPI

    return MPI.SUM


def _mpi_in_place():
    from mpi4py import MPI

    return MPI.IN_PLACE
