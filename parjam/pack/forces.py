"""Energy, forces and Hessian of one packing whose positions live in a distributed PETSc Vec
(PETSc's split into contiguous blocks of particle ids, block size d).

FIRE does not run here: parjam.pack.fire hands the positions to a ``parjam.pack.engine.SlabEngine``
(``start_engine``), which spreads the particles over the slabs of the spatial decomposition and
keeps no array of length N on any rank; at the end (``stop_engine``) they come back to the Vec.
Nothing here gathers the whole configuration: files and checkpoints go by rows
(parjam.pack.staterows, parjam.files.checkpointio), and the gathers tests and scripts want (all N positions
or engine values on every rank) are parjam.testing.gather's, outside the packing path.

For Newton and single evaluations the Verlet list holds the pairs that touch a rank's block
rows: on one rank from linked cells in compiled code (cellsearch.cell_pairs; in a box of fewer
than 3 cells a side a k-d tree), on several from the slabs of parjam.net.domain (``slab_pairs``:
the block rows visit their slabs, one ghost exchange, each pair back to the block rows of its
ends), so no rank gathers the positions; each rank computes the forces on its particles only
and assembles its rows of Newton's Hessian from the halo positions.  Between rebuilds a force
evaluation fetches just the positions of the particles those pairs touch (its own and a halo of
ghosts, one VecScatter; their diameters are fetched once per rebuild).  Forces on a particle
are summed over its pairs in global (i, j) order, so they are bitwise independent of the number
of ranks; the energy is an exact sum (parjam.net.exactsum) and max |F| a maximum, so they are
too.  Newton's matrix comes from the contacts (``contact_rows``, ``contact_operator``), each
row summed in global (i, j) order, for the rank-independent solvers of parjam.pack.newtonsolve.
"""

import numpy as np

from parjam import env
from parjam.net import exactsum
from parjam.pack import cellsearch, kernels
from parjam.vib import hessian
from parjam.net.domain import SlabDomain, send_rows
from parjam.pack.engine import SlabEngine
from parjam.logevents import ASSEMBLY, FORCE, HALO, REBUILD, event
from parjam.net.system import min_image, neighbour_pairs_touching, pair_geometry, wrap


class ForceField:
    """Forces, energy and Hessian of a packing (diameters, box L, alpha) on communicator comm."""

    def __init__(self, comm, diam, L, d, alpha, eps=1.0, skin=None, n=None):
        """``diam``: all N diameters (not kept), or given ``n`` only those of this rank's block
        rows (hessian.row_range(n, comm)): then no rank holds N of them."""
        PETSc = env.petsc()
        self.comm = comm
        self.mpi = comm.tompi4py()
        diam = np.asarray(diam, dtype=np.float64)
        self.n = len(diam) if n is None else int(n)
        self.d = d
        self.alpha = alpha
        self.eps = eps
        self.lo, self.hi = hessian.row_range(self.n, comm)
        if n is None:
            self.dmin, self.dmax = float(diam.min()), float(diam.max())
            diam = diam[self.lo:self.hi]
        elif len(diam) != self.hi - self.lo:
            raise ValueError(f"{len(diam)} diameters for block rows [{self.lo}, {self.hi})")
        else:
            ends = np.array([-diam.min(), diam.max()] if len(diam) else [-np.inf, -np.inf])
            self.mpi.Allreduce(ends.copy(), ends, op=_max())
            self.dmin, self.dmax = -float(ends[0]), float(ends[1])
        self.skin = 0.2 * self.dmin if skin is None else skin
        self.diam_rows = np.array(diam)  # the diameters of the block rows
        self.x = PETSc.Vec().createMPI(((self.hi - self.lo) * d, self.n * d), bsize=d, comm=comm)
        self.engine = None  # the SlabEngine while FIRE runs (start_engine)
        self.set_box(L)
        self.n_force_calls = 0
        self.n_rebuilds = 0
        self._hess = None  # Hessian kept between Newton steps (see hessian())
        self._hess_pairs = None
        self.newton_ksp = None  # its solver (parjam.pack.newtonsolve), kept by minimize.newton
        self.halo_scatter = self.halo_x = None  # see _build_halo

    def set_box(self, L):
        self.L = float(L)
        cut = self.dmax + self.skin
        if self.L <= 2.0 * cut:
            self.skin = max(0.0, 0.49 * self.L - self.dmax)
        self.pairs = None

    def vec(self):
        """A new Vec with the layout of the positions."""
        return self.x.duplicate()

    # --- positions -----------------------------------------------------------------------
    def set_positions(self, pos):
        """Scatter full positions (same array on every rank) into the distributed Vec."""
        self.x.array[:] = pos[self.lo:self.hi].ravel()

    def set_rows(self, ids, x):
        """Positions ``x`` of the particles ``ids`` (any rows of any rank, each particle on one
        rank) handed to their block rows of the Vec (collective; no rank holds all N)."""
        ranges = np.asarray(self.x.getOwnershipRanges()) // self.d
        dest = np.searchsorted(ranges, ids, side="right") - 1
        _, got = send_rows(self.comm, dest, ids, {"x": np.asarray(x, dtype=np.float64)})
        self.x.array[:] = got["x"].ravel()

    def wrap(self):
        """Fold the owned positions back into [0, L)."""
        arr = self.x.array
        arr[:] = wrap(arr, self.L)

    def local(self, vec):
        return vec.array.reshape(-1, self.d)

    # --- neighbour list (Verlet list with skin) ------------------------------------------------
    def _stale(self, own):
        """True when the list must be rebuilt: none yet, or some particle moved more than half
        the skin since the last rebuild (each rank checks its own ``own`` positions; one MPI
        max)."""
        if self.pairs is None:
            return True
        disp = min_image(own - self.ref_own, self.L)
        moved = np.einsum("ij,ij->i", disp, disp).max() if len(disp) else 0.0
        return self.mpi.allreduce(moved, op=_max()) >= (0.5 * self.skin) ** 2

    def _update_pairs(self, pos=None):
        own = self.local(self.x) if pos is None else pos[self.lo:self.hi]
        if self._stale(own):
            self._rebuild(pos)

    def _rebuild(self, pos=None):
        """Verlet list at the current positions (collective), and the halo for it.  On one rank
        (or given the full positions ``pos``) the compiled cell search over all of them; on
        several, ``slab_pairs``: no rank gathers the positions."""
        with event(REBUILD):
            cut = self.dmax + self.skin
            if pos is None and self.comm.getSize() > 1:
                self.pairs = self.slab_pairs(cut)
            else:
                pos = self.local(self.x) if pos is None else pos
                # linked cells in compiled code; the k-d tree when the box holds < 3 cells a side
                self.pairs = cellsearch.cell_pairs(wrap(np.asarray(pos), self.L), self.L, cut,
                                                   self.lo, self.hi)
                if self.pairs is None:
                    self.pairs = neighbour_pairs_touching(pos, self.L, cut, self.lo, self.hi)
            self.pairs_i = np.ascontiguousarray(self.pairs[:, 0])
            self.pairs_j = np.ascontiguousarray(self.pairs[:, 1])
            self.ref_own = np.array(self.local(self.x) if pos is None else pos[self.lo:self.hi])
            self.n_rebuilds += 1
            self._build_halo()

    def rebuild_neighbours(self):
        """Rebuild the Verlet list and its halo now, at the current positions (collective): what
        an evaluation does when the list is stale; for timing the neighbour search alone
        (scripts/hpc/profile_phases.py)."""
        self._rebuild()

    def slab_pairs(self, cut):
        """The pairs (i < j) closer than ``cut`` with an end in this rank's block rows, in
        (i, j) order, as the cell search lists them, found on the slabs of parjam.net.domain: the
        block rows go to their slabs, one ghost exchange, the pairs of owned particles and
        ghosts, and each pair back to the block rows of both its ends (collective; O(N/P))."""
        ids = np.arange(self.lo, self.hi, dtype=np.int64)
        xw = wrap(np.array(self.local(self.x)), self.L)
        dom = SlabDomain.balanced(self.mpi, self.L, xw)
        xs, gs, _ = dom.migrate(xw, ids)
        halo = dom.halo(xs, gs, cut)
        found = dom.neighbour_pairs(xs, halo, cut)
        gid = np.concatenate([gs, halo.ids])
        a, b = gid[found[:, 0]], gid[found[:, 1]]
        i, j = np.minimum(a, b), np.maximum(a, b)
        ranges = np.asarray(self.x.getOwnershipRanges()) // self.d
        oi = np.searchsorted(ranges, i, side="right") - 1
        oj = np.searchsorted(ranges, j, side="right") - 1
        two = oj != oi
        key = np.concatenate([i, i[two]]) * self.n + np.concatenate([j, j[two]])
        got, _ = send_rows(self.mpi, np.concatenate([oi, oj[two]]), key)
        key = np.unique(got)  # a pair across slabs is found on both
        return np.stack([key // self.n, key % self.n], axis=1)

    def _build_halo(self):
        """The particles this rank's pairs touch, sorted (its own form the contiguous block
        [halo_lo, halo_hi)), the pairs renumbered into that list, and the scatter that fetches
        their positions.  On one rank the halo is everything and no scatter is needed."""
        PETSc = env.petsc()
        if self.halo_scatter is not None:
            self.halo_scatter.destroy()
            self.halo_x.destroy()
            self.halo_scatter = self.halo_x = None
        if self.comm.getSize() == 1:
            self.halo_i, self.halo_j, self.halo_diam = self.pairs_i, self.pairs_j, self.diam_rows
            self.halo_lo, self.halo_hi = 0, self.n
            return
        need = np.union1d(np.arange(self.lo, self.hi, dtype=np.int64),
                          np.concatenate([self.pairs_i, self.pairs_j]))
        self.halo_i = np.ascontiguousarray(np.searchsorted(need, self.pairs_i), dtype=np.int64)
        self.halo_j = np.ascontiguousarray(np.searchsorted(need, self.pairs_j), dtype=np.int64)
        self.halo_diam = self.rows_of(need)
        self.halo_lo = int(np.searchsorted(need, self.lo))
        self.halo_hi = self.halo_lo + (self.hi - self.lo)
        index = PETSc.IS().createBlock(self.d, need.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        self.halo_x = PETSc.Vec().createSeq(len(need) * self.d, bsize=self.d,
                                            comm=PETSc.COMM_SELF)
        self.halo_scatter = PETSc.Scatter().create(self.x, index, self.halo_x, None)
        index.destroy()

    def rows_of(self, need):
        """Diameters of the particles ``need`` (sorted global ids), fetched from their block
        rows (collective; one VecScatter)."""
        PETSc = env.petsc()
        dv = PETSc.Vec().createMPI((self.hi - self.lo, self.n), comm=self.comm)
        dv.array[:] = self.diam_rows
        index = PETSc.IS().createGeneral(need.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        out = PETSc.Vec().createSeq(len(need), comm=PETSc.COMM_SELF)
        sc = PETSc.Scatter().create(dv, index, out, None)
        sc.scatter(dv, out, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        got = np.array(out.array_r)
        for obj in (sc, out, index, dv):
            obj.destroy()
        return got

    def _halo_positions(self):
        """Positions of the halo particles (collective on several ranks), (n_halo, d)."""
        if self.halo_scatter is None:
            return self.x.array_r.reshape(self.n, self.d)
        PETSc = env.petsc()
        with event(HALO):
            self.halo_scatter.scatter(self.x, self.halo_x, PETSc.InsertMode.INSERT,
                                      PETSc.ScatterMode.FORWARD)
        return self.halo_x.array_r.reshape(-1, self.d)

    def renew_neighbours(self):
        """Drop the neighbour list: the next evaluation rebuilds it at the current positions.
        Newton calls this, so that its matrix pattern (hence the MUMPS ordering and round-off)
        depends on the positions only, not on when the list was last built; a run resumed from a
        checkpoint (parjam.files.checkpoint) then reaches the same minimum bitwise."""
        self.pairs = None

    def contacts(self):
        """Pairs touching owned particles that overlap: (i, j, r_ij, r, sigma), from the halo
        positions (minimize's force scale)."""
        self._update_pairs()
        rij, r, sigma = pair_geometry(self._halo_positions(), self.L, self.halo_diam,
                                      np.stack([self.halo_i, self.halo_j], axis=1))
        c = r < sigma
        return self.pairs[c, 0], self.pairs[c, 1], rij[c], r[c], sigma[c]

    # --- energy and forces ---------------------------------------------------------------
    def evaluate(self, f):
        """Write the forces on owned particles into Vec f; return the total energy (an exact
        sum: the same bits on any number of ranks)."""
        self.n_force_calls += 1
        if self._stale(self.x.array_r.reshape(-1, self.d)):
            self._rebuild()
        pos = self._halo_positions()
        acc = np.zeros(exactsum.ACC_LEN, dtype=np.int64)
        with event(FORCE):
            kernels.pair_forces(self.halo_i, self.halo_j, pos, self.halo_diam, self.L,
                                self.alpha, self.eps, self.halo_lo, self.halo_hi, self.local(f),
                                acc)
        if self.comm.getSize() > 1:
            from mpi4py import MPI

            self.mpi.Allreduce(MPI.IN_PLACE, acc, op=MPI.SUM)
        return exactsum.value(acc)

    # --- FIRE on the spatial decomposition (parjam.pack.fire) ---------------------------------------
    def start_engine(self, v_block=None):
        """A SlabEngine holding the current positions (and ``v_block``, velocities of this rank's
        block rows) on the slabs (collective)."""
        x = np.array(self.x.array_r).reshape(-1, self.d)
        self.engine = SlabEngine(self.comm, self.L, self.alpha, self.eps, self.skin, x,
                                 np.arange(self.lo, self.hi, dtype=np.int64),
                                 self.diam_rows, v_block)
        return self.engine

    def block_rows(self, values):
        """Per-particle ``values`` of the engine's rows, as this rank's block rows (collective)."""
        ranges = np.asarray(self.x.getOwnershipRanges()) // self.d
        return self.engine.to_blocks(ranges, values)

    def sync_engine(self):
        """The engine's positions into the Vec (collective)."""
        self.x.array[:] = self.block_rows(self.engine.xu).ravel()

    def stop_engine(self):
        """The engine's positions back into the Vec, and the engine dropped (collective)."""
        self.sync_engine()
        self.n_rebuilds += self.engine.n_rebuilds
        self.engine = None

    def max_norm(self, f):
        """max_i |F_i| over all particles (Euclidean norm per particle)."""
        fl = self.local(f)
        m = np.sqrt(np.einsum("ij,ij->i", fl, fl)).max() if len(fl) else 0.0
        return self.mpi.allreduce(m, op=_max())

    def hessian(self, shift=0.0, kind="full"):
        """The distributed Hessian at the current positions (all particles, rattlers included).

        Its pattern is the neighbour list (non-touching pairs hold zero blocks), so between
        neighbour-list rebuilds the same Mat is refilled in place and a factorisation of it can
        reuse its symbolic phase (ordering and analysis).
        """
        self._update_pairs()
        pos = self._halo_positions()  # this rank's particles and their neighbours: no gather
        with event(ASSEMBLY):
            return self._assemble_hessian(pos, shift, kind)

    def _assemble_hessian(self, pos, shift, kind):
        """The Hessian from the halo positions ``pos`` (the pairs renumbered into the halo)."""
        rij, r, sigma = pair_geometry(pos, self.L, self.halo_diam,
                                      np.stack([self.halo_i, self.halo_j], axis=1))
        touch = r < sigma
        blocks = np.zeros((len(r), self.d, self.d))
        blocks[touch] = hessian.contact_blocks(rij[touch], r[touch], sigma[touch], self.alpha,
                                               self.eps, kind)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        if self._hess is not None and self._hess_pairs is self.pairs:
            indptr, cols, vals = hessian.local_csr(self.comm, self.n, self.d, i, j, blocks, shift)
            self._hess.setValuesCSR(indptr, cols, vals)
            self._hess.assemble()
        else:
            if self._hess is not None:
                self._hess.destroy()
            self._hess = hessian.assemble(self.comm, self.n, self.d, i, j, blocks, shift)
            self._hess_pairs = self.pairs
        return self._hess

    # --- Newton's matrix from the contacts (parjam.pack.newtonsolve) ----------------------------
    def _contact_blocks(self, kind="full"):
        """The contacts among the pairs (closer than sigma_ij) as global ids, halo rows and
        their d x d blocks of Eq. (1) (parjam.vib.hessian.contact_blocks)."""
        self._update_pairs()
        pos = self._halo_positions()
        rij, r, sigma = pair_geometry(pos, self.L, self.halo_diam,
                                      np.stack([self.halo_i, self.halo_j], axis=1))
        c = r < sigma
        blocks = hessian.contact_blocks(rij[c], r[c], sigma[c], self.alpha, self.eps, kind)
        return self.pairs[c, 0], self.pairs[c, 1], self.halo_i[c], self.halo_j[c], blocks

    def contact_rows(self, shift=0.0):
        """This rank's block rows of H + shift I from the contacts alone, as a scalar CSR
        (indptr, global columns, values): each row is summed over its contacts in global
        (i, j) order (parjam.vib.hessian.local_csr), so the rows, and their pattern, are the
        same bits on any number of ranks (collective)."""
        i, j, _, _, blocks = self._contact_blocks()
        return hessian.local_csr(self.comm, self.n, self.d, i, j, blocks, shift)

    def contact_operator(self, shift=0.0):
        """(apply, precondition, release) on this rank's rows: v -> (H + shift I) v and the
        point-block Jacobi r -> D^-1 r (D: the d x d diagonal blocks of H + shift I), for
        (n_own, d) arrays, valid until the next neighbour rebuild; release() frees them.  A product sums each particle's contacts in global (i, j) order, first as
        the upper end, then as the lower one (the force kernel's order): the same bits on any
        number of ranks (collective per call)."""
        PETSc = env.petsc()
        gi, gj, hi_, hj_, K = self._contact_blocks()
        d, lo, hi = self.d, self.lo, self.hi
        own_i, own_j = (gi >= lo) & (gi < hi), (gj >= lo) & (gj < hi)
        idx = np.concatenate([gj[own_j], gi[own_i]]) - lo
        n_own = hi - lo
        diag = np.empty((n_own, d, d))
        Kc = np.concatenate([K[own_j], K[own_i]])
        for a in range(d):
            for b in range(d):
                diag[:, a, b] = np.bincount(idx, weights=Kc[:, a, b], minlength=n_own)
        diag += shift * np.eye(d)
        inv = np.linalg.inv(diag) if n_own else diag
        vec, halo = self.vec(), None
        if self.halo_scatter is not None:
            halo = self.halo_x.duplicate()

        def release():
            for obj in (vec, halo):
                if obj is not None:
                    obj.destroy()

        def apply(v):
            vec.array[:] = v.reshape(-1)
            if halo is None:
                vh = v
            else:
                self.halo_scatter.scatter(vec, halo, PETSc.InsertMode.INSERT,
                                          PETSc.ScatterMode.FORWARD)
                vh = halo.array_r.reshape(-1, d)
            dv = vh[hj_] - vh[hi_]  # v_j - v_i
            w = np.zeros_like(dv)  # K (v_j - v_i), components in a fixed order
            for a in range(d):
                for b in range(d):
                    w[:, a] += K[:, a, b] * dv[:, b]
            wc = np.concatenate([w[own_j], -w[own_i]])
            out = np.empty((n_own, d))
            for a in range(d):
                out[:, a] = np.bincount(idx, weights=wc[:, a], minlength=n_own)
            return out + shift * v

        def precondition(r):
            out = np.zeros_like(r)
            for a in range(d):
                for b in range(d):
                    out[:, a] += inv[:, a, b] * r[:, b]
            return out

        return apply, precondition, release

    def destroy(self):
        if self._hess is not None:
            self._hess.destroy()
        if self.newton_ksp is not None:
            self.newton_ksp.destroy()
        if self.halo_scatter is not None:
            self.halo_scatter.destroy()
            self.halo_x.destroy()
        self.x.destroy()


def _max():
    from mpi4py import MPI

    return MPI.MAX
