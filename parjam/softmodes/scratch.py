"""The null basis out of core (``parjam softmodes --scratch DIR``): each rank writes its own rows
of every accepted column block to a file in a temporary directory under DIR, and every later use
reads it back in column blocks (deflation of the next block, the gap solve, the Eq. 3 check, the
trial energies, the output) or in row chunks (Gram matrices, extension, f(x), the rotation of
the Appendix, written back in place).  A cut then holds O(N columns) of basis in memory instead
of N d n_soft (docs/results/benchmarks.md).

:class:`ScratchBasis` is a row-split n_loc x k array on disk: ``V[a:z]`` reads rows a..z-1 of all
columns, ``V[a:z] = R`` writes them, ``V.shape`` is its size; :meth:`ScratchBasis.column_blocks`
yields the stored blocks.  Its blocks are laid out one after the other, each row-major, so a
column block is one contiguous read and a row chunk one read per block.  Reads and writes are
``os.pread``/``os.pwrite`` into fresh arrays: nothing stays mapped, so the basis never counts in
the resident set (unlike ``numpy.memmap``, whose touched pages do).

The scratch is asked for, never automatic: the basis size is known only after the inertia
count, and whether its file is better on disk than in memory depends on the machine's free
memory and disk, which the user knows (the estimate is N' d n_soft 8 bytes per cut).

:func:`scratch_space` makes the temporary directory and removes it, with its files, on exit,
also on error.
"""

import contextlib
import os
import shutil
import tempfile

import numpy as np

from parjam.errors import ParjamError

ITEM = 8  # bytes per float64


def check_directory(path):
    """One line (ParjamError) unless ``path`` is a writable directory: called before any work."""
    if not os.path.isdir(path):
        raise ParjamError(f"--scratch {path}: not a directory")
    if not os.access(path, os.W_OK | os.X_OK):
        raise ParjamError(f"--scratch {path}: not writable")


class ScratchSpace:
    """A temporary directory of one rank; :meth:`basis` makes a :class:`ScratchBasis` in it."""

    def __init__(self, path):
        self.path = path
        self.files = []

    def basis(self, nloc):
        out = ScratchBasis(os.path.join(self.path, f"basis{len(self.files)}.f8"), nloc)
        self.files.append(out)
        return out

    def close(self):
        for f in self.files:
            f.close()
        shutil.rmtree(self.path, ignore_errors=True)


@contextlib.contextmanager
def scratch_space(comm, directory):
    """A :class:`ScratchSpace` under ``directory`` for this rank (None: yields None, in core),
    removed with its files when the block exits, normally or by an exception."""
    if directory is None:
        yield None
        return
    try:
        path = tempfile.mkdtemp(prefix=f"parjam-softmodes-r{comm.getRank()}-", dir=directory)
    except OSError as exc:
        raise ParjamError(f"--scratch {directory}: {exc.strerror}") from None
    space = ScratchSpace(path)
    try:
        yield space
    finally:
        space.close()


class ScratchBasis:
    """This rank's n_loc rows of a basis stored on disk in column blocks (see the module)."""

    def __init__(self, path, nloc):
        self.path = path
        self.nloc = nloc
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        self.blocks = []  # (first column, width, byte offset)
        self.end = 0  # bytes written

    @property
    def shape(self):
        return (self.nloc, sum(w for _, w, _ in self.blocks))

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def write(self, offset, array):
        buf = memoryview(np.ascontiguousarray(array, dtype=np.float64)).cast("B")
        done = 0
        while done < len(buf):
            done += os.pwrite(self.fd, buf[done:], offset + done)

    def read(self, offset, shape):
        out = np.empty(shape)
        buf = memoryview(out).cast("B")
        done = 0
        while done < len(buf):
            got = os.preadv(self.fd, [buf[done:]], offset + done)
            if got <= 0:
                raise ParjamError(f"short read from the scratch file {self.path}")
            done += got
        return out

    def append(self, B):
        """Store the columns B (n_loc x w) after the ones already there."""
        assert B.shape[0] == self.nloc
        self.write(self.end, B)
        self.blocks.append((self.shape[1], B.shape[1], self.end))
        self.end += B.size * ITEM

    def column_blocks(self):
        """The stored blocks, one n_loc x w array at a time (a fresh read each)."""
        for _, w, off in self.blocks:
            yield self.read(off, (self.nloc, w))

    def columns(self, c0, c1):
        """Columns c0..c1-1 (all local rows), read from the blocks that hold them."""
        c1 = min(c1, self.shape[1])
        out = np.empty((self.nloc, max(c1 - c0, 0)))
        for first, w, off in self.blocks:
            a, z = max(c0, first), min(c1, first + w)
            if a < z:
                out[:, a - c0:z - c0] = self.read(off, (self.nloc, w))[:, a - first:z - first]
        return out

    def rows_range(self, key):
        if not isinstance(key, slice) or key.step not in (None, 1):
            raise TypeError("a scratch basis is indexed by row slices only")
        return range(self.nloc)[key]

    def __getitem__(self, key):
        r = self.rows_range(key)
        out = np.empty((len(r), self.shape[1]))
        if len(r):
            for first, w, off in self.blocks:
                out[:, first:first + w] = self.read(off + r.start * w * ITEM, (len(r), w))
        return out

    def __setitem__(self, key, value):
        r = self.rows_range(key)
        value = np.asarray(value, dtype=np.float64)
        if value.shape != (len(r), self.shape[1]):
            raise ValueError(f"rows of shape {value.shape} for {len(r)} x {self.shape[1]}")
        for first, w, off in self.blocks:
            if len(r):
                self.write(off + r.start * w * ITEM, value[:, first:first + w])
