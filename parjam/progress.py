"""Progress lines on stderr, written by world rank 0 only (quiet with -q).

With several rank groups (``parjam pack`` with fewer ranks than members, or several members per
rank), each group's rank 0 makes progress lines for its own members; a :class:`Relay` carries
them to world rank 0, which prints them between its own lines, so that one process writes the
whole log and every member is heard from, not only those of world rank 0."""

import sys
import time

_TAG = 7101


class Relay:
    """Lines from other ranks to world rank 0, over a private duplicate of ``mpi_comm``
    (collective to create and to :meth:`close`)."""

    def __init__(self, mpi_comm):
        self.comm = mpi_comm.Dup()
        self.rank = self.comm.Get_rank()
        self.pending = []
        self.open = self.comm.Get_size() - 1  # ranks whose closing message is still to come

    def send(self, line):
        self.pending.append(self.comm.isend(line, dest=0, tag=_TAG))

    def drain(self, block=False):
        """World rank 0: print what arrived (and, with ``block``, wait for every rank's close)."""
        from mpi4py import MPI

        status = MPI.Status()
        while self.open > 0 and (block or self.comm.iprobe(MPI.ANY_SOURCE, _TAG, status)):
            line = self.comm.recv(source=MPI.ANY_SOURCE, tag=_TAG)
            if line is None:
                self.open -= 1
            else:
                print(line, file=sys.stderr, flush=True)

    def close(self):
        """Every rank: the others send their end marker, world rank 0 prints until all ended."""
        from mpi4py import MPI

        if self.rank == 0:
            self.drain(block=True)
        else:
            self.send(None)
            MPI.Request.Waitall(self.pending)
        self.pending = []
        self.comm.Free()


class Progress:
    def __init__(self, comm=None, quiet=False, prefix="", relay=None):
        rank = comm.Get_rank() if comm is not None else 0
        self.enabled = (not quiet) and rank == 0
        self.quiet = quiet
        self.prefix = prefix
        self.relay = relay
        self.t0 = time.time()

    def __call__(self, msg):
        if not self.enabled:
            return
        line = f"[{time.time() - self.t0:8.1f} s] {self.prefix}{msg}"
        if self.relay is not None and self.relay.rank != 0:
            self.relay.send(line)
            return
        if self.relay is not None:
            self.relay.drain()
        print(line, file=sys.stderr, flush=True)

    def sub(self, prefix):
        child = Progress(quiet=not self.enabled, prefix=self.prefix + prefix, relay=self.relay)
        child.t0 = self.t0
        return child

    def group(self, comm, prefix):
        """Lines of a rank group (``comm``, a PETSc or mpi4py communicator): its rank 0 speaks,
        through the relay when that is not world rank 0."""
        child = Progress(comm, self.quiet, self.prefix + prefix, self.relay)
        child.t0 = self.t0
        return child

    def throttled(self, interval=10.0):
        """A callable printing at most once per ``interval`` seconds (for inner loops such as
        FIRE steps, whose count per second varies by orders of magnitude with N)."""
        last = [time.time()]

        def emit(msg):
            now = time.time()
            if now - last[0] >= interval:
                last[0] = now
                self(msg)

        return emit
