"""The files of a member's checkpoint (parjam.files.checkpoint), append-only and by row blocks: no rank
holds all N positions to write or to read them.

Layout (FORMAT 2), for member M of run directory DIR:

- ``DIR/.checkpoint/memberMMMM.h5``, the *index*: a small HDF5 file, written atomically
  (in memory, then fsync and rename: parjam.files.outputs) by the group's rank 0, always last.  Its
  attributes hold the format, the run's parameters (JSON) and a generation number; a group
  ``done/KKKKK`` per finished minimisation and a group ``pending`` for the one in progress hold
  their scalars (box edge, result, counters; FIRE's time step, mixing, step...) and the name of
  the *piece* file with their rows.  The index names the valid pieces: nothing else counts.
- ``DIR/.checkpoint/memberMMMM.d/``, the pieces: ``doneKKKKK.gGGGGGGG.h5`` (dataset ``pos``,
  (N, d), the positions a minimisation ended at) and ``pending.gGGGGGGG.h5`` (``pos`` and ``v``,
  the positions and FIRE velocities of a snapshot), in particle-id order.  Each is written once,
  by row blocks (parjam.files.rowio.rows_file: rank 0 receives every rank's block in pieces of at most
  rowio.CHUNK_BYTES, the disk space reserved first, then fsync and an atomic rename), and never
  rewritten: a piece is named with the generation of the index that will first name it (one
  more than the index on disk), so it never replaces a piece the index on disk names.

Order of a write: pieces, then the index, then the pieces no index names any more are removed.
Killed at any moment, the directory holds the old index and the pieces it names (a piece
written after it is an orphan, removed at the next write), or the new index and its pieces.
Each rank reads its own block rows of a piece (h5py hyperslabs; independent read-only opens of
one file are safe with the serial h5py): a resume reads no row twice and no rank reads all N.
"""

import os

import h5py
import numpy as np

from parjam.files import h5md, inputs, rowio
from parjam.pack.minimize import FireState, MinimiseState, MinResult

FORMAT = 2
RESULT_KEYS = ("status", "energy", "fmax", "fire_steps", "newton_steps")
STATE_KEYS = ("round", "tol", "fire_rel", "fire_steps", "newton_steps")
FIRE_KEYS = ("dt", "a", "n_pos", "step")


def pieces_dir(index):
    """The directory of the pieces of the index file ``index``."""
    return os.path.splitext(index)[0] + ".d"


def piece_name(kind, generation, call=None):
    """``doneKKKKK.gGGGGGGG.h5`` or ``pending.gGGGGGGG.h5``."""
    stem = "pending" if call is None else f"done{call:05d}"
    return f"{stem}.g{generation:07d}.h5"


def write_rows(comm, path, blocks):
    """A piece: the datasets ``blocks`` (name -> this rank's block rows, in rank order = id
    order) written by row blocks and renamed into place (collective; parjam.files.rowio)."""
    nbytes = comm.allreduce(sum(int(np.asarray(b).nbytes) for b in blocks.values()))
    with rowio.rows_file(comm, path, nbytes) as out:
        for name, block in blocks.items():
            out.rows(name, np.ascontiguousarray(block, dtype=np.float64))


def read_rows(path, name, lo, hi):
    """Rows [lo, hi) of dataset ``name`` of a piece (this rank only)."""
    with _h5(path) as f:
        ds = f[name]
        if ds.ndim != 2 or ds.shape[0] < hi:
            raise ValueError(f"{os.path.basename(path)}: /{name} has shape {ds.shape}")
        return np.array(ds[lo:hi], dtype=np.float64)


def write_index(path, params, generation, done, pending):
    """The index: ``done`` (dicts with file, L, result, force_calls) and ``pending`` (None or
    a dict with file, call, L, force_calls, state: a MinimiseState whose FIRE velocities are in
    the piece) of the run of parameters ``params`` (a JSON string)."""
    with h5md.atomic_h5(path) as f:
        f.attrs.update({"format": FORMAT, "params": params, "generation": generation})
        f.create_group("done")
        for k, rec in enumerate(done):
            res = rec["result"]
            f.create_group(f"done/{k:05d}").attrs.update(
                {"file": rec["file"], "L": rec["L"], "force_calls": rec["force_calls"],
                 **{key: getattr(res, key) for key in RESULT_KEYS}})
        if pending is not None:
            st = pending["state"]
            f.create_group("pending").attrs.update(
                {"file": pending["file"], "call": pending["call"], "L": pending["L"],
                 "force_calls": pending["force_calls"],
                 **{key: getattr(st, key) for key in STATE_KEYS},
                 **{key: getattr(st.fire, key) for key in FIRE_KEYS}})


def _h5(path):
    """An HDF5 file of the checkpoint, read only if it is a regular file (a FIFO put there would
    block the open): ValueError, the damaged-checkpoint error, otherwise."""
    what = inputs.kind(path)
    if what is not None:
        raise ValueError(f"{path} is {what}")
    return h5py.File(path, "r")


def read_format(path):
    """The format number of an index (1: parjam's earlier whole-file checkpoint)."""
    with _h5(path) as f:
        return int(f.attrs["format"])


def read_index(path):
    """{"params", "generation", "done", "pending"} of an index of FORMAT; the pending state's
    FIRE velocities are None (each rank reads its rows of the piece).  Raises OSError,
    KeyError or ValueError for a damaged one, or one whose pieces are missing."""
    here = pieces_dir(path)
    with _h5(path) as f:
        if int(f.attrs["format"]) != FORMAT:
            raise ValueError(f"format {f.attrs['format']} (this parjam reads {FORMAT})")
        done = []
        for name in sorted(f["done"]):
            a = f["done"][name].attrs
            res = MinResult(str(a["status"]), float(a["energy"]), float(a["fmax"]),
                            int(a["fire_steps"]), int(a["newton_steps"]))
            done.append({"file": str(a["file"]), "L": float(a["L"]), "result": res,
                         "force_calls": int(a["force_calls"])})
        pending = None
        if "pending" in f:
            a = f["pending"].attrs
            fs = FireState(None, float(a["dt"]), float(a["a"]), int(a["n_pos"]), int(a["step"]))
            st = MinimiseState(int(a["round"]), float(a["tol"]), float(a["fire_rel"]),
                               int(a["fire_steps"]), int(a["newton_steps"]), fs)
            pending = {"file": str(a["file"]), "call": int(a["call"]), "L": float(a["L"]),
                       "force_calls": int(a["force_calls"]), "state": st}
        out = {"params": str(f.attrs["params"]), "generation": int(f.attrs["generation"]),
               "done": done, "pending": pending}
    for rec in done + ([pending] if pending else []):
        if not os.path.isfile(os.path.join(here, rec["file"])):
            raise ValueError(f"its piece {rec['file']} is missing")
    return out


def remove_unnamed(index, keep):
    """Remove the files of the pieces directory of ``index`` other than ``keep`` (the pieces
    the index on disk names): orphans of an interrupted write, pieces of an older index, a
    killed writer's temporaries.  Rank 0 only, with no write of this member in progress."""
    here = pieces_dir(index)
    if not os.path.isdir(here):
        return
    for name in set(os.listdir(here)) - set(keep):
        try:
            os.remove(os.path.join(here, name))
        except OSError:  # gone already, or not a file: left alone
            pass


def remove_all(index):
    """The index first (the checkpoint is gone from then on), then its pieces and directory."""
    if os.path.exists(index):
        os.remove(index)
    remove_unnamed(index, ())
    try:
        os.rmdir(pieces_dir(index))
    except OSError:
        pass
