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

The files (parjam.files.checkpointio: an index ``DIR/.checkpoint/memberMMMM.h5`` naming append-only
piece files in ``memberMMMM.d/``) are written by the member's group: a finished minimisation's
positions always, as a piece, when it ends (``finish``); the index, and with it a snapshot of
the minimisation in progress, at most every ``every`` seconds (and nothing at all with
``every <= 0``).  They are removed when the member's results are written.

Memory: no rank holds all N rows of anything.  Positions and velocities go from the
ranks that own them (the force field's block rows; a snapshot's from the FIRE engine's slab
rows, handed to the block rows first) to rank 0 in pieces of at most rowio.CHUNK_BYTES, which
it writes as it receives them; on resume each rank reads its own block rows of a replayed
record and of the snapshot from the files.  The index records the run's parameters and parjam's
version and is ignored (with a note) if they differ, as is a checkpoint of the format before
this one (FORMAT 1, the whole-file checkpoint); a record whose volume fraction is not the one
the protocol asks for ends the replay there.
"""

import json
import os
import time

from parjam import __version__, faults
from parjam.files import checkpointio
from parjam.errors import ParjamError

DIRECTORY = ".checkpoint"
FORMAT = checkpointio.FORMAT


def path_for(out, member):
    """The index file of member ``member``'s checkpoint (its pieces: checkpointio.pieces_dir)."""
    return os.path.join(out, DIRECTORY, f"member{member:04d}.h5")


class Checkpoint:
    """Record of one member's minimisations on communicator ``comm`` (its group)."""

    def __init__(self, path, comm, every, params, progress=None):
        self.path = path
        self.pieces = checkpointio.pieces_dir(path)
        self.mpi = comm.tompi4py()
        self.every = float(every)
        # the parjam version too: another version may take the protocol another way
        self.params = json.dumps({**params, "parjam": __version__}, sort_keys=True)
        # finished minimisations: dicts with file (the piece of their positions), L, result,
        # force_calls; the one in progress: dict with file, call, L, force_calls, state
        self.done = []
        self.pending = None
        self.generation = 0  # of the index on disk; new pieces are named with the next one
        self._written = time.monotonic()
        self.loaded = self._load(progress)

    # --- reading -------------------------------------------------------------------------------
    def _load(self, progress):
        """Read the index on rank 0 and share it; False if there is none (or it is foreign)."""
        data, note = None, None
        if self.mpi.Get_rank() == 0 and os.path.exists(self.path):
            try:
                data = checkpointio.read_index(self.path)
            except (OSError, KeyError, ValueError) as exc:
                note = f"checkpoint {self.path} unreadable ({exc}): starting afresh"
                if _format_of(self.path) == 1:
                    note = (f"checkpoint {self.path} is of parjam's earlier format 1 (this "
                            f"parjam writes {FORMAT}): ignored, starting afresh")
            else:
                if data["params"] != self.params:
                    data, note = None, f"checkpoint {self.path} is of other parameters: ignored"
        data, note = self.mpi.bcast((data, note), root=0)
        if note and progress is not None:
            progress(note)
        if data is None:
            return False
        self.done, self.pending = data["done"], data["pending"]
        self.generation = data["generation"]
        return True

    def _piece(self, rec):
        return os.path.join(self.pieces, rec["file"])

    def replay_rows(self, call, ff):
        """Set the positions of force field ``ff`` to those of finished minimisation ``call``:
        each rank reads its block rows of the record's piece (collective)."""
        mine = ff.local(ff.x)
        mine[:] = self._read_rows(self.done[call], "pos", ff)

    def _read_rows(self, rec, name, ff):
        """This rank's block rows of dataset ``name`` of the piece of ``rec`` (collective: a
        damaged piece is one line on every rank)."""
        rows, problem = None, None
        try:
            rows = checkpointio.read_rows(self._piece(rec), name, ff.lo, ff.hi)
        except (OSError, KeyError, ValueError) as exc:
            problem = f"checkpoint {self.path}: cannot read {rec['file']} ({exc})"
        problems = [p for p in self.mpi.allgather(problem) if p]
        if problems:
            raise ParjamError(problems[0])
        return rows

    def finished(self, call):
        """The record of minimisation number ``call`` if it finished before, else None."""
        return self.done[call] if call < len(self.done) else None

    def discard_from(self, call):
        """Forget minimisation ``call`` and all after it (the protocol went another way)."""
        del self.done[call:]
        self.pending = None

    def in_progress(self, call, ff):
        """(force evaluations so far, MinimiseState) of minimisation ``call`` if it was
        interrupted, its positions set in ``ff`` and its velocities this rank's block rows
        (collective: each rank reads its rows of the snapshot); else None."""
        p = self.pending
        if p is None or p["call"] != call or len(self.done) != call:
            return None
        ff.local(ff.x)[:] = self._read_rows(p, "pos", ff)
        p["state"].fire.v = self._read_rows(p, "v", ff)
        return p["force_calls"], p["state"]

    # --- writing -------------------------------------------------------------------------------
    def _due(self):
        """The same decision on every rank of the group (rank 0's clock)."""
        if self.every <= 0:
            return False
        due = time.monotonic() - self._written >= self.every if self.mpi.Get_rank() == 0 else None
        return self.mpi.bcast(due, root=0)

    def _write_piece(self, name, blocks):
        """A piece named ``name`` from every rank's block rows (collective)."""
        try:
            checkpointio.write_rows(self.mpi, os.path.join(self.pieces, name), blocks)
        except ParjamError as exc:  # raised on every rank alike (rowio)
            raise ParjamError(f"cannot write checkpoint {self.path}: {exc}") from None

    def finish(self, call, ff, L, result, force_calls):
        """Minimisation ``call`` ended at the positions of force field ``ff`` (box edge ``L``)
        with ``result``: its positions written as a piece now, from every rank's block rows, the
        index when due (collective)."""
        name = checkpointio.piece_name("done", self.generation + 1, call)
        self._write_piece(name, {"pos": ff.local(ff.x)})
        self.done.append({"file": name, "L": float(L), "result": result,
                          "force_calls": int(force_calls)})
        self.pending = None
        if self._due():
            self.write()

    def snapshot(self, call, ff, L, calls_before):
        """A hook for ``minimize.minimize``: record minimisation ``call`` in progress, when due
        (collective: every rank of the group calls it); ``calls_before`` is ff's force-evaluation
        count when the minimisation began.  The positions and velocities go from the FIRE
        engine's rows to the block rows and from there to the piece: no rank gathers them."""

        def hook(make_state):
            if not self._due():
                return
            ff.sync_engine()  # the engine's positions into ff's block rows
            state = make_state()  # FIRE's velocities: this rank's block rows
            name = checkpointio.piece_name("pending", self.generation + 1)
            self._write_piece(name, {"pos": ff.local(ff.x), "v": state.fire.v})
            state.fire.v = None  # in the piece only
            self.pending = {"file": name, "call": call, "L": float(L), "state": state,
                            "force_calls": ff.n_force_calls - calls_before}
            self.write()
            # written: a later write either finishes this minimisation or snapshots it anew
            self.pending = None

        return hook

    def write(self):
        """Write the index now (group rank 0; collective: every rank of the group calls it),
        naming the pieces written so far, then remove the pieces it no longer names."""
        problem = None
        if self.mpi.Get_rank() == 0:
            try:
                write_file(self.path, self.params, self.done, self.pending,
                           self.generation + 1)
            except (OSError, ParjamError) as exc:  # e.g. a full disk
                problem = f"cannot write checkpoint {self.path}: {exc}"
            else:
                named = [rec["file"] for rec in self.done]
                checkpointio.remove_unnamed(self.path, named + ([self.pending["file"]]
                                                                if self.pending else []))
        if self.mpi.Get_size() > 1:  # the group's ranks end together, with one line
            problem = self.mpi.bcast(problem, root=0)
        if problem:
            raise ParjamError(problem)
        self.generation += 1
        self._written = time.monotonic()
        faults.point("pack.checkpoint")  # PARJAM_FAULT testing hook (parjam/faults.py)

    def remove(self):
        """The member is written: its checkpoint goes (the index first)."""
        if self.mpi.Get_rank() == 0:
            checkpointio.remove_all(self.path)


def remove_empty_directory(out):
    """At the end of a run (no group writes any more): DIR/.checkpoint if nothing is left in it."""
    try:
        os.rmdir(os.path.join(out, DIRECTORY))
    except OSError:  # a member's checkpoint is still there (it failed), or there never was one
        pass


def write_file(path, params, done, pending, generation=1):
    """The index of a checkpoint (checkpointio.write_index): the run parameters, the finished
    minimisations and the one in progress, with the names of their pieces."""
    checkpointio.write_index(path, params, generation, done, pending)


def _format_of(path):
    try:
        return checkpointio.read_format(path)
    except (OSError, KeyError, ValueError):
        return None
