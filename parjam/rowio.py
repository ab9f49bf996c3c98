"""Packing files read by row ranges: no rank holds all N positions (issue 19).

The installed h5py is serial (no ``mpio`` driver), so every rank opens the file read-only by
itself (independent opens; concurrent readers of one HDF5 file are safe) and reads only its
contiguous block of rows of /particles/all/position/value (the last frame of a time series)
and /particles/all/diameter, as h5py hyperslabs.  The small metadata (box edges, /parameters)
is read by every rank.  Files are the ones of docs/file-format.md, unchanged.

Validation gives the one-line errors of parjam.io.read_packing before any work: the layout and
parameters are checked identically on every rank, the values of each rank's rows locally and
the first problem (in rank order) raised on every rank.  Coinciding centres, which
read_packing finds with a k-d tree of all N, are found by the distributed contact search
(``network``: a contact with r below DUPLICATE_TOL x the smallest diameter).

Writing stays on rank 0 (parjam.io, parjam.outputs): the outputs of analyze, modes, dos and
moduli are O(N' k) at most and are written by one rank.
"""

import os
from dataclasses import dataclass

import h5py
import numpy as np

from parjam import active, io
from parjam.domain import as_mpi
from parjam.errors import ParjamError

POSITIONS, DIAMETERS = "particles/all/position/value", "particles/all/diameter"
SPECIES = "particles/all/species"


@dataclass
class Rows:
    """This rank's rows [start, stop) of a packing file and its global parameters."""

    path: str
    n: int
    d: int
    start: int
    stop: int
    pos: np.ndarray
    diam: np.ndarray
    L: float
    alpha: float
    eps: float
    meta: dict
    species_ok: bool = True  # the species of these rows are integers (or there are none)

    @property
    def ids(self):
        return np.arange(self.start, self.stop, dtype=np.int64)


def collective(comm, problem):
    """Raise the first rank's problem (a message or None) on every rank."""
    problems = [p for p in comm.allgather(problem) if p]
    if problems:
        raise ParjamError(problems[0])


def read_rows(comm, path):
    """This rank's block of rows of a packing file, validated (collective)."""
    comm = as_mpi(comm)
    path = str(path)
    head, problem = None, None
    try:
        head = read_block(comm, path)
    except ParjamError as exc:
        problem = str(exc)
    except (OSError, RuntimeError, KeyError) as exc:  # truncated or corrupted inside
        problem = f"{path}: unreadable HDF5 file ({exc})"
    collective(comm, problem)
    rows = head
    problem = io.value_problem(path, rows.pos, rows.diam, np.full(rows.d, rows.L), rows.L)
    collective(comm, problem or (None if rows.species_ok else
                                 f"{path}: species must be {rows.n} integers"))
    rows.pos = np.mod(rows.pos, rows.L)
    return rows


def read_block(comm, path):
    """Metadata checks and this rank's rows, unvalidated values."""
    if not os.path.isfile(path):
        raise ParjamError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    with h5py.File(path, "r") as f:
        pos = io.checked_dataset(f, POSITIONS, path, (2, 3))
        diam = io.checked_dataset(f, DIAMETERS, path, (1,))
        edges = io.box_edges(f, path)
        params = dict(f["parameters"].attrs) if "parameters" in f else {}
        frame = pos.shape[1:] if pos.ndim == 3 else pos.shape
        if pos.ndim == 3 and pos.shape[0] == 0:
            raise ParjamError(f"{path}: the position time series holds no frame")
        L = io.check_layout(path, frame, diam.shape, edges)
        alpha, eps, meta = io.model_parameters(path, params)
        n, d = frame
        start, stop = active.row_block(n, comm)
        x = pos[-1, start:stop] if pos.ndim == 3 else pos[start:stop]
        rows = Rows(path, n, d, start, stop, np.asarray(x, dtype=float),
                    np.asarray(diam[start:stop], dtype=float), L, alpha, eps, meta)
        if isinstance(f.get(SPECIES), h5py.Dataset):  # read_packing's check, on these rows
            species = io.checked_dataset(f, SPECIES, path, (1,))
            if species.shape != (n,):
                raise ParjamError(f"{path}: species must be {n} integers")
            own = np.asarray(species[start:stop], dtype=float)
            rows.species_ok = bool(np.all(own == np.round(own)))
        return rows


def network(comm, source):
    """The distributed active network of a packing file (a path, or its ``read_rows``), read by
    row ranges (collective)."""
    rows = source if isinstance(source, Rows) else read_rows(comm, source)
    try:
        return active.build(comm, rows.pos, rows.diam, rows.ids, rows.L, rows.alpha, rows.eps,
                            coincide=io.DUPLICATE_TOL)
    except ValueError as exc:  # raised on every rank alike (active.check_distinct)
        raise ParjamError(f"{rows.path}: {exc}") from None
