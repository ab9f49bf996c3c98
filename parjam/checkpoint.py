"""Checkpoints inside one member's packing protocol, so that a killed or requeued ``parjam pack``
resumes where it was instead of from the random start (a 3D N = 10^5 member near jamming needs
hours of FIRE on a few cores: longer than many batch jobs may run).

The protocol of a member (phi_c search, ladder, target pressures) is a sequence of
minimisations (``Jammer.relax``) whose every decision depends only on their results.  A
checkpoint holds, for each finished minimisation, its result and the configuration it ended in,
and for the one in progress, the positions and FIRE's state (velocities, time step, mixing,
counters; ``minimize.MinimiseState``).  On resume the finished minimisations are replayed from the
record, without computing, and the one in progress continues its FIRE run.  The forces do not
depend on when the neighbour list was built (overlapping pairs are summed in (i, j) order), and
Newton rebuilds the list when it starts (so its matrix pattern depends on the positions only):
a resumed run follows the uninterrupted trajectory bitwise, on one rank.

The file (``DIR/.checkpoint/memberMMMM.h5``) is rewritten atomically by rank 0 of the member's
group at most every ``every`` seconds (and not at all with ``every <= 0``), and removed when the
member's results are written.

Memory (issue 18): only rank 0 holds the finished minimisations' positions (N x d each): it
writes them, and the file is written atomically from an in-memory HDF5 image (parjam.outputs'
policy: a full disk never leaves a partial file), so the writer holds the whole image at a write
anyway; streaming it block by block would need an append-only checkpoint format.  A finished
minimisation's positions reach rank 0 one rank's block at a time (``finish``); on resume each
rank receives only its block rows of a replayed record (``replay_rows``).  A snapshot of a
minimisation in progress gathers positions and velocities (parjam.fire's state) for the write
and drops them after it.  It records the run's parameters and parjam's version and is
ignored (with a note) if they differ; a record whose volume fraction is not the one the protocol
asks for ends the replay there.
"""

import json
import os
import time

import h5py
import numpy as np

from parjam import __version__, faults, io
from parjam.errors import ParjamError
from parjam.minimize import FireState, MinimiseState, MinResult

DIRECTORY = ".checkpoint"
FORMAT = 1


def path_for(out, member):
    return os.path.join(out, DIRECTORY, f"member{member:04d}.h5")


class Checkpoint:
    """Record of one member's minimisations on communicator ``comm`` (its group)."""

    def __init__(self, path, comm, every, params, progress=None):
        self.path = path
        self.mpi = comm.tompi4py()
        self.every = float(every)
        # the parjam version too: another version may take the protocol another way
        self.params = json.dumps({**params, "parjam": __version__}, sort_keys=True)
        self.done = []  # finished minimisations: dicts with pos, L, result, force_calls
        self.pending = None  # the one in progress: dict with call, pos, L, state
        self._written = time.monotonic()
        self.loaded = self._load(progress)

    # --- reading -------------------------------------------------------------------------------
    def _load(self, progress):
        """Read the file on rank 0 and share it; False if there is none (or it is foreign)."""
        data, note = None, None
        if self.mpi.Get_rank() == 0 and os.path.exists(self.path):
            try:
                data = _read(self.path)
            except (OSError, KeyError, ValueError) as exc:
                note = f"checkpoint {self.path} unreadable ({exc}): starting afresh"
            else:
                if data["params"] != self.params:
                    data, note = None, f"checkpoint {self.path} is of other parameters: ignored"
        root = self.mpi.Get_rank() == 0
        # the other ranks get the records without their positions (replay_rows sends them)
        meta = None if data is None else {
            "done": [{k: v for k, v in rec.items() if k != "pos"} for rec in data["done"]],
            "pending": data["pending"]}
        meta, note = self.mpi.bcast((meta, note), root=0)
        if note and progress is not None:
            progress(note)
        if meta is None:
            return False
        self.done = data["done"] if root else meta["done"]
        self.pending = meta["pending"]
        return True

    def replay_rows(self, call, ff):
        """Set the positions of force field ``ff`` to those of finished minimisation ``call``:
        rank 0 sends each rank its block rows (collective)."""
        ranges = np.asarray(ff.x.getOwnershipRanges()) // ff.d
        mine = ff.local(ff.x)
        if self.mpi.Get_rank() == 0:
            pos = self.done[call]["pos"]
            for r in range(1, self.mpi.Get_size()):
                self.mpi.Send(np.ascontiguousarray(pos[ranges[r]:ranges[r + 1]]), dest=r)
            mine[:] = pos[ranges[0]:ranges[1]]
        else:
            rows = np.empty_like(mine)
            self.mpi.Recv(rows, source=0)
            mine[:] = rows

    def finished(self, call):
        """The record of minimisation number ``call`` if it finished before, else None."""
        return self.done[call] if call < len(self.done) else None

    def discard_from(self, call):
        """Forget minimisation ``call`` and all after it (the protocol went another way)."""
        del self.done[call:]
        self.pending = None

    def in_progress(self, call):
        """(positions, force evaluations so far, MinimiseState) of minimisation ``call`` if it
        was interrupted."""
        p = self.pending
        if p is not None and p["call"] == call and len(self.done) == call:
            return p["pos"], p["force_calls"], p["state"]
        return None

    # --- writing -------------------------------------------------------------------------------
    def _due(self):
        """The same decision on every rank of the group (rank 0's clock)."""
        if self.every <= 0:
            return False
        due = time.monotonic() - self._written >= self.every if self.mpi.Get_rank() == 0 else None
        return self.mpi.bcast(due, root=0)

    def finish(self, call, ff, L, result, force_calls):
        """Minimisation ``call`` ended at the positions of force field ``ff`` (box edge ``L``)
        with ``result``; written when due (collective: the positions go to rank 0, one rank's
        block rows at a time; the other ranks keep the record without them)."""
        self.done.append({"pos": self.rows_to_root(ff), "L": float(L), "result": result,
                          "force_calls": int(force_calls)})
        self.pending = None
        if self._due():
            self.write()

    def snapshot(self, call, ff, L, calls_before):
        """A hook for ``minimize.minimize``: record minimisation ``call`` in progress, when due
        (collective: every rank of the group calls it); ``calls_before`` is ff's force-evaluation
        count when the minimisation began."""

        def hook(make_state):
            if not self._due():
                return
            pos = np.array(ff.gather())  # before make_state(), which reuses the gather buffer
            self.pending = {"call": call, "pos": pos, "L": float(L), "state": make_state(),
                            "force_calls": ff.n_force_calls - calls_before}
            self.write()
            # written: a later write either finishes this minimisation or snapshots it anew
            self.pending = None
            ff.drop_gather()

        return hook

    def rows_to_root(self, ff):
        """The positions of ``ff`` on rank 0 as an (N, d) array, received one rank's block rows
        at a time (collective); None on the other ranks."""
        mine = np.ascontiguousarray(ff.local(ff.x))
        if self.mpi.Get_rank() != 0:
            self.mpi.Send(mine, dest=0)
            return None
        ranges = np.asarray(ff.x.getOwnershipRanges()) // ff.d
        pos = np.empty((ff.n, ff.d))
        pos[ranges[0]:ranges[1]] = mine
        for r in range(1, self.mpi.Get_size()):
            self.mpi.Recv(pos[ranges[r]:ranges[r + 1]], source=r)
        return pos

    def write(self):
        """Write the checkpoint now (group rank 0; collective: every rank of the group calls it)."""
        if self.mpi.Get_rank() == 0:
            try:
                write_file(self.path, self.params, self.done, self.pending)
            except OSError as exc:  # e.g. a full disk: end every rank with one line
                raise ParjamError(f"cannot write checkpoint {self.path}: {exc}",
                                  collective=False) from None
        self._written = time.monotonic()
        faults.point("pack.checkpoint")  # PARJAM_FAULT testing hook (parjam/faults.py)

    def remove(self):
        """The member is written: its checkpoint goes."""
        if self.mpi.Get_rank() == 0 and os.path.exists(self.path):
            os.remove(self.path)


def remove_empty_directory(out):
    """At the end of a run (no group writes any more): DIR/.checkpoint if nothing is left in it."""
    try:
        os.rmdir(os.path.join(out, DIRECTORY))
    except OSError:  # a member's checkpoint is still there (it failed), or there never was one
        pass


def write_file(path, params, done, pending):
    """A checkpoint file: the run parameters, the finished minimisations and the one in progress."""
    with io.atomic_h5(path) as f:
        f.attrs["format"] = FORMAT
        f.attrs["params"] = params
        for k, rec in enumerate(done):
            g = f.create_group(f"done/{k:05d}")
            g["pos"] = rec["pos"]
            res = rec["result"]
            g.attrs.update({"L": rec["L"], "force_calls": rec["force_calls"],
                            "status": res.status, "energy": res.energy, "fmax": res.fmax,
                            "fire_steps": res.fire_steps, "newton_steps": res.newton_steps})
        if pending is not None:
            g = f.create_group("pending")
            st = pending["state"]
            g["pos"] = pending["pos"]
            g["v"] = st.fire.v
            g.attrs.update({"call": pending["call"], "L": pending["L"], "round": st.round,
                            "force_calls": pending["force_calls"],
                            "tol": st.tol, "fire_rel": st.fire_rel, "fire_steps": st.fire_steps,
                            "newton_steps": st.newton_steps, "dt": st.fire.dt, "a": st.fire.a,
                            "n_pos": st.fire.n_pos, "step": st.fire.step})


def _read(path):
    with h5py.File(path, "r") as f:
        if int(f.attrs["format"]) != FORMAT:
            raise ValueError(f"format {f.attrs['format']} (this parjam reads {FORMAT})")
        done = []
        for name in sorted(f.get("done", {})):
            g = f["done"][name]
            a = g.attrs
            res = MinResult(str(a["status"]), float(a["energy"]), float(a["fmax"]),
                            int(a["fire_steps"]), int(a["newton_steps"]))
            done.append({"pos": g["pos"][()], "L": float(a["L"]), "result": res,
                         "force_calls": int(a["force_calls"])})
        pending = None
        if "pending" in f:
            g = f["pending"]
            a = g.attrs
            fs = FireState(g["v"][()], float(a["dt"]), float(a["a"]), int(a["n_pos"]),
                           int(a["step"]))
            st = MinimiseState(int(a["round"]), float(a["tol"]), float(a["fire_rel"]),
                               int(a["fire_steps"]), int(a["newton_steps"]), fs)
            pending = {"call": int(a["call"]), "pos": g["pos"][()], "L": float(a["L"]),
                       "force_calls": int(a["force_calls"]), "state": st}
        return {"params": str(f.attrs["params"]), "done": done, "pending": pending}
