"""Packing files read by row ranges: no rank holds all N positions.

The installed h5py is serial (no ``mpio`` driver), so every rank opens the file read-only by
itself (independent opens; concurrent readers of one HDF5 file are safe) and reads only its
contiguous block of rows of /particles/all/position/value (the last frame of a time series)
and /particles/all/diameter, as h5py hyperslabs.  The small metadata (box edges, /parameters)
is read by every rank.  Files are the ones of docs/reference/file-format.md, unchanged.

Validation gives the one-line errors of parjam.files.h5md.read_packing before any work: the layout and
parameters are checked identically on every rank, the values of each rank's rows locally and
the first problem (in rank order) raised on every rank.  Coinciding centres, which
read_packing finds with a k-d tree of all N, are found where the rows become a network
(parjam.net.active.from_rows: a contact with r below DUPLICATE_TOL x the smallest diameter).

Writing by row blocks (:func:`rows_file`, :class:`RowFile`): a dataset whose rows are spread
over the ranks is written without any rank holding all of them.  With this serial h5py, rank 0
creates the file and each dataset with its full shape and attributes, then receives every
rank's block in turn, in global row order (rank r's rows follow rank r-1's), in pieces of at
most ``CHUNK_BYTES``, and writes each as a hyperslab: rank 0 holds its own block and one piece.
Rows keyed by particle ids in another order (the active network's rows on P > 1) first go to
the rank whose contiguous id block holds them (parjam.net.active.home_rows, called by the
writer's caller), so the file's rows stay in particle-id order.  Where h5py is built with MPI (``h5py.get_config().mpi``), every rank opens
the file with the ``mpio`` driver instead and writes its own hyperslab collectively (that path
cannot run on this machine's serial h5py: it is kept small and untested here).

The write is atomic (parjam.files.outputs' policy: ``.NAME.tmpPID``, fsync, rename) but not built in
memory as ``outputs.atomic_h5`` does (that would hold the whole file on rank 0): the temporary
file's size bound is reserved on disk first (``posix_fallocate``), so a full disk is the one
line ``PATH: cannot write (No space left on device)`` before HDF5 writes anything, and HDF5
writes through a file object (h5py's ``fileobj`` driver) whose end of file is the data written,
not the reservation.  Every method is collective: a failure on rank 0 is raised on every rank.

Why one file of ~530 lines: reading and writing by row blocks share the row split
(``active.row_block``), the collective one-line error policy and the layout of parjam's files;
the sections are reading, writing, and the per-particle datasets of parjam's files.
"""

import contextlib
import errno
import io as pyio
import os
from dataclasses import dataclass

import h5py
import numpy as np

from parjam import env
from parjam.files import h5md, inputs, outputs
from parjam.net.active import row_block
from parjam.net.domain import as_mpi
from parjam.errors import ParjamError
from parjam.net.system import wrap

POSITIONS, DIAMETERS = "particles/all/position/value", "particles/all/diameter"
SPECIES = "particles/all/species"


READ, WRITE = "parjam: read rows", "parjam: write rows"
_events = {}


def event(name):
    """The PETSc log event ``name`` (READ or WRITE), registered once: ``-log_view`` shows the
    reading and the writing of every command built on this module."""
    if name not in _events:
        _events[name] = env.petsc().Log.Event(name)
    return _events[name]


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
    species: np.ndarray = None  # these rows' species (float, as read), None: the file has none

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
    with event(READ):
        return read_validated(as_mpi(comm), path)


def read_validated(comm, path):
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
    problem = h5md.value_problem(path, rows.pos, rows.diam, np.full(rows.d, rows.L), rows.L)
    collective(comm, problem or (None if rows.species_ok else
                                 f"{path}: species must be {rows.n} integers"))
    rows.pos = wrap(rows.pos, rows.L)  # read_packing's fold, bit for bit
    return rows


def read_block(comm, path):
    """Metadata checks and this rank's rows, unvalidated values."""
    inputs.require(path)  # a FIFO, a directory, a loop: named, and never opened
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    with h5py.File(path, "r") as f:
        pos = h5md.checked_dataset(f, POSITIONS, path, (2, 3))
        diam = h5md.checked_dataset(f, DIAMETERS, path, (1,))
        edges = h5md.box_edges(f, path)
        params = dict(f["parameters"].attrs) if "parameters" in f else {}
        frame = pos.shape[1:] if pos.ndim == 3 else pos.shape
        if pos.ndim == 3 and pos.shape[0] == 0:
            raise ParjamError(f"{path}: the position time series holds no frame")
        L = h5md.check_layout(path, frame, diam.shape, edges)
        alpha, eps, meta = h5md.model_parameters(path, params)
        n, d = frame
        start, stop = row_block(n, comm)
        x = pos[-1, start:stop] if pos.ndim == 3 else pos[start:stop]
        rows = Rows(path, n, d, start, stop, np.asarray(x, dtype=float),
                    np.asarray(diam[start:stop], dtype=float), L, alpha, eps, meta)
        if isinstance(f.get(SPECIES), h5py.Dataset):  # read_packing's check, on these rows
            species = h5md.checked_dataset(f, SPECIES, path, (1,))
            if species.shape != (n,):
                raise ParjamError(f"{path}: species must be {n} integers")
            own = np.asarray(species[start:stop], dtype=float)
            rows.species_ok = bool(np.all(own == np.round(own)))
            rows.species = own
        return rows


# --- writing by row blocks ---------------------------------------------------------------------
CHUNK_BYTES = 16 << 20  # the largest piece of a block sent to rank 0 at once
HEADROOM_BYTES = 1 << 20  # reserved beyond the data for HDF5's headers, attributes, small sets
PARALLEL_H5 = bool(h5py.get_config().mpi)  # h5py built with MPI: the mpio driver


class ReservedFile(pyio.RawIOBase):
    """A file descriptor as a Python file object whose end of file is what was written, not
    its size on disk (the reservation beyond it): what h5py's ``fileobj`` driver reads and
    writes through."""

    def __init__(self, fd):
        super().__init__()
        self.fd, self.pos, self.size = fd, 0, 0

    def readable(self):
        return True

    def writable(self):
        return True

    def seekable(self):
        return True

    def seek(self, offset, whence=os.SEEK_SET):
        self.pos = {os.SEEK_SET: 0, os.SEEK_CUR: self.pos, os.SEEK_END: self.size}[whence] + offset
        return self.pos

    def tell(self):
        return self.pos

    def readinto(self, buf):
        want = max(min(len(buf), self.size - self.pos), 0)
        data = os.pread(self.fd, want, self.pos)
        buf[:len(data)] = data
        self.pos += len(data)
        return len(data)

    def write(self, buf):
        done = os.pwrite(self.fd, buf, self.pos)
        self.pos += done
        self.size = max(self.size, self.pos)
        return done

    def truncate(self, size=None):
        self.size = self.pos if size is None else size
        os.ftruncate(self.fd, self.size)
        return self.size


def reserve(fd, nbytes):
    """Allocate ``nbytes`` on disk for ``fd`` (ENOSPC here, before any HDF5 write); a file
    system without allocation support is left to the write itself."""
    if nbytes <= 0 or not hasattr(os, "posix_fallocate"):
        return
    try:
        os.posix_fallocate(fd, 0, int(nbytes))
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            return
        raise


@contextlib.contextmanager
def reserved_h5(path, nbytes):
    """An h5py File written to disk atomically (``outputs.atomic_path``) in ``nbytes`` reserved
    for it first: one rank's file that is never held in memory whole."""
    with outputs.atomic_path(path) as tmp:
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        try:
            reserve(fd, nbytes + HEADROOM_BYTES)
            raw = ReservedFile(fd)
            with h5py.File(raw, "w") as f:
                yield f
            os.ftruncate(fd, raw.size)  # the reservation beyond the end of the file released
        finally:
            os.close(fd)


def problem_of(call, *args):
    """``call(*args)``'s ParjamError or OSError as a one-line message (None: it succeeded)."""
    try:
        call(*args)
    except ParjamError as exc:
        return str(exc)
    except OSError as exc:  # an HDF5 write error (h5py raises OSError)
        return f"cannot write ({exc.strerror or exc})"
    return None


class RowFile:
    """An HDF5 file written by every rank together (from :func:`rows_file`): small replicated
    content through :meth:`meta`, row-distributed datasets through :meth:`rows`.  ``f`` is the
    h5py File on the ranks that write (rank 0; every rank with the mpio driver), else None."""

    def __init__(self, comm, path, f, parallel=False, chunk_bytes=CHUNK_BYTES):
        self.comm, self.path, self.f, self.parallel = comm, path, f, parallel
        self.chunk_bytes = chunk_bytes

    @property
    def root(self):
        return self.comm.Get_rank() == 0

    def raise_collective(self, problem):
        """Raise rank 0's problem (only rank 0 writes) or, with the mpio driver, the first
        rank's, on every rank."""
        if self.comm.Get_size() > 1:
            problem = (next((p for p in self.comm.allgather(problem) if p), None)
                       if self.parallel else self.comm.bcast(problem, root=0))
        if problem:
            raise ParjamError(problem if problem.startswith(self.path) else
                              f"{self.path}: {problem}")

    def meta(self, write, make_args=tuple):
        """``write(f, *make_args())``: groups, attributes and small datasets every rank has
        alike.  ``make_args`` runs on rank 0 only (its result is broadcast for the mpio driver,
        whose metadata writes are collective with equal values on every rank)."""
        args = make_args() if self.root else None
        if self.parallel and self.comm.Get_size() > 1:
            args = self.comm.bcast(args, root=0)
        problem = problem_of(write, self.f, *args) if self.f is not None else None
        self.raise_collective(problem)

    def rows(self, name, block, axis=0, attrs=None):
        """The dataset ``name`` made of every rank's ``block`` stacked along ``axis`` in rank
        order (the other axes equal on every rank; a rank may hold no rows).  Collective."""
        with event(WRITE):
            self.write_rows(name, np.asarray(block), axis, attrs)

    def write_rows(self, name, block, axis, attrs):
        shapes = self.comm.allgather((block.shape, block.dtype.str))
        counts = [shape[axis] for shape, _ in shapes]
        rest = {shape[:axis] + shape[axis + 1:] for shape, _ in shapes}
        if len(rest) != 1 or len({dt for _, dt in shapes}) != 1:
            raise ParjamError(f"{self.path}: /{name}: the ranks' blocks differ in shape or type "
                              f"({shapes[:4]}...)")
        shape = block.shape[:axis] + (sum(counts),) + block.shape[axis + 1:]
        start = sum(counts[:self.comm.Get_rank()])
        if self.parallel:
            self.raise_collective(problem_of(self.write_collective, name, shape, block, axis,
                                             start, attrs))
        elif self.root:
            self.raise_collective(self.receive_and_write(name, shape, block, axis, counts,
                                                         attrs))
        else:
            self.send(block, axis)
            self.raise_collective(None)

    def pieces(self, n, row_bytes):
        """(first row, rows) of the pieces of at most ``chunk_bytes`` that n rows of
        ``row_bytes`` each are sent in (at least one row per piece)."""
        step = max(self.chunk_bytes // max(row_bytes, 1), 1)
        return [(a, min(step, n - a)) for a in range(0, n, step)]

    def send(self, block, axis):
        row_bytes = block.itemsize * int(np.prod(block.shape)) // max(block.shape[axis], 1)
        for a, m in self.pieces(block.shape[axis], row_bytes):
            piece = np.ascontiguousarray(np.take(block, np.arange(a, a + m), axis=axis))
            self.comm.Send(piece, dest=0, tag=7)

    def receive_and_write(self, name, shape, block, axis, counts, attrs):
        """Rank 0: create the dataset, write its own block, then each rank's pieces in turn;
        after a failed write it still receives everything (no rank is left blocked)."""
        problem = problem_of(self.create, name, shape, block.dtype, attrs)
        other = shape[:axis] + shape[axis + 1:]
        row_bytes = block.itemsize * int(np.prod(other))
        start = 0
        for r, count in enumerate(counts):
            for a, m in self.pieces(count, row_bytes):
                if r == 0:
                    piece = np.take(block, np.arange(a, a + m), axis=axis)
                else:
                    piece = np.empty(shape[:axis] + (m,) + shape[axis + 1:], block.dtype)
                    self.comm.Recv(piece, source=r, tag=7)
                if problem is None:
                    problem = problem_of(self.put, name, axis, start + a, piece)
            start += count
        return problem

    def create(self, name, shape, dtype, attrs):
        ds = self.f.create_dataset(name, shape=shape, dtype=dtype)
        for key, val in (attrs or {}).items():
            ds.attrs[key] = val

    def put(self, name, axis, first, piece):
        sel = (slice(None),) * axis + (slice(first, first + piece.shape[axis]),)
        if piece.shape[axis]:
            self.f[name][sel] = piece

    def write_collective(self, name, shape, block, axis, start, attrs):
        """The mpio driver: every rank creates the dataset and writes its own hyperslab."""
        self.create(name, shape, block.dtype, attrs)
        ds = self.f[name]
        sel = (slice(None),) * axis + (slice(start, start + block.shape[axis]),)
        with ds.collective:
            ds[sel] = block


@contextlib.contextmanager
def rows_file(comm, path, nbytes, chunk_bytes=CHUNK_BYTES):
    """A :class:`RowFile` at ``path`` (collective), written atomically when the block succeeds;
    ``nbytes``: the data's size (every rank passes the same), reserved on disk first.  A
    failure leaves no file and no temporary, on every rank the same one-line ParjamError."""
    comm = as_mpi(comm)
    path = os.fspath(path)
    if PARALLEL_H5 and comm.Get_size() > 1:
        with parallel_file(comm, path, nbytes) as f:
            yield RowFile(comm, path, f, parallel=True, chunk_bytes=chunk_bytes)
        return
    stack = contextlib.ExitStack()
    f, problem = None, None
    if comm.Get_rank() == 0:
        try:
            f = stack.enter_context(reserved_h5(path, nbytes))
        except ParjamError as exc:
            problem = str(exc)
    out = RowFile(comm, path, f, chunk_bytes=chunk_bytes)
    out.raise_collective(problem)
    try:
        yield out
    except BaseException as exc:
        stack.__exit__(type(exc), exc, exc.__traceback__)  # the temporary removed
        raise
    close_on_root(comm, stack)


def close_on_root(comm, stack):
    """Close rank 0's ExitStack (the temporary file renamed into place) and raise its problem,
    if any, on every rank (collective)."""
    problem = None
    if comm.Get_rank() == 0:
        try:
            stack.close()
        except ParjamError as exc:
            problem = str(exc)
    problem = comm.bcast(problem, root=0)
    if problem:
        raise ParjamError(problem)


def check_space(path, nbytes):
    """ParjamError ``PATH: cannot write (No space left on device)`` when the file system of
    ``path`` (its nearest existing directory) has less than ``nbytes`` free."""
    directory = os.path.dirname(outputs.target(path))
    while directory and not os.path.isdir(directory):
        directory = os.path.dirname(directory)
    st = os.statvfs(directory or ".")
    if st.f_bavail * st.f_frsize < nbytes:
        raise ParjamError(f"{path}: cannot write ({os.strerror(errno.ENOSPC)})")


@contextlib.contextmanager
def parallel_file(comm, path, nbytes):
    """The mpio driver (h5py built with MPI): every rank opens rank 0's temporary name; rank 0
    checks the free space first (HDF5 truncates the file it creates: no reservation) and
    renames the file when every rank has closed it."""
    tmp, problem = None, None
    stack = contextlib.ExitStack()
    if comm.Get_rank() == 0:
        try:
            check_space(path, nbytes + HEADROOM_BYTES)
            tmp = stack.enter_context(outputs.atomic_path(path))
        except ParjamError as exc:
            problem = str(exc)
    tmp, problem = comm.bcast((tmp, problem), root=0)
    if problem:
        raise ParjamError(problem)
    try:
        with h5py.File(tmp, "w", driver="mpio", comm=comm) as f:
            yield f
    except BaseException as exc:
        if comm.Get_rank() == 0:
            stack.__exit__(type(exc), exc, exc.__traceback__)
        raise
    close_on_root(comm, stack)


# --- the per-particle datasets of parjam's files -----------------------------------------------
def write_particle_rows(out, rows, group="all"):
    """/particles/GROUP's position/value (1, N, d), diameter and species (int32; zeros when the
    file has none) from every rank's file rows (a :class:`Rows`), as h5md.write_particles writes
    them; the box and time series around them come from ``h5md.particles_header`` (in a
    ``meta`` call)."""
    out.rows(f"particles/{group}/position/value", rows.pos[None], axis=1)
    out.rows(f"particles/{group}/diameter", rows.diam, attrs=h5md.diameter_attrs())
    species = (np.zeros(len(rows.diam), np.int32) if rows.species is None
               else rows.species.astype(np.int32))
    out.rows(f"particles/{group}/species", species)


def write_packing_rows(comm, path, part, d, L, alpha, eps, phi, observables, parameters,
                       prov=None):
    """A packing file (h5md.write_packing's layout and content) from every rank's rows ``part``
    (collective; no rank holds all N or all Nc rows): its particles in id order (``pos``,
    ``diam``, ``species``, ``rattler``) and its contacts in the file's order (``contacts``,
    ``overlap``, ``force``, ``stiffness``), parjam.pack.staterows.PackingRows.
    ``observables``: the global /observables values (the network's summary, ``stress_tensor``
    and extras); ``parameters``: the /parameters attributes beyond alpha, epsilon and phi."""
    comm = as_mpi(comm)
    n_all, nc_all = comm.allreduce(np.array([len(part.diam), len(part.overlap)]))
    nbytes = n_all * (8 * d + 8 + 4 + 1) + nc_all * (16 + 24)

    def header(f, prov_, d_, L_):
        h5md.write_h5md_header(f, prov_)
        h5md.particles_header(f, d_, L_)

    def tail(f, obs, alpha_, eps_, phi_, params):
        h5md.link_contacts(f)
        h5md.write_observables(f, d, obs)
        h5md.write_parameters(f, alpha_, eps_, phi_, params)

    units = h5md.contact_attrs()
    with rows_file(comm, path, nbytes) as out:
        out.meta(header, lambda: (prov, d, L))
        out.rows("particles/all/position/value", np.asarray(part.pos, float)[None], axis=1)
        out.rows("particles/all/diameter", np.asarray(part.diam, float),
                 attrs=h5md.diameter_attrs())
        out.rows("particles/all/species", np.asarray(part.species, np.int32))
        out.rows("particles/all/rattler", np.asarray(part.rattler).astype(np.int8))
        out.rows("connectivity/contacts", np.asarray(part.contacts).reshape(-1, 2))
        out.rows("connectivity/overlap", np.asarray(part.overlap, float))
        out.rows("connectivity/force", np.asarray(part.force, float), attrs=units["force"])
        out.rows("connectivity/stiffness", np.asarray(part.stiffness, float),
                 attrs=units["stiffness"])
        out.meta(tail, lambda: (observables, alpha, eps, phi, parameters))
