"""Progress lines on stderr, written by world rank 0 only (quiet with -q).

With several rank groups (``parjam pack`` with fewer ranks than members, or several members per
rank), each group's rank 0 makes progress lines for its own members; a :class:`Relay` carries
them to world rank 0, which prints them between its own lines, so that one process writes the
whole log and every member is heard from, not only those of world rank 0.  Every line is
stamped by world rank 0's clock when it is printed, so the times of the log never go backwards
(a relayed line's own rank started its clock at another moment; its line arrives when rank 0
next speaks or at the end)."""

import sys
import time

_TAG = 7101


def member(m, total=None):
    """How every message names member ``m`` (its 0-based index, the MMMM of its files
    memberMMMM_*): counted from 1, "member 1 of 8"."""
    return f"member {m + 1}" + (f" of {total}" if total is not None else "")


class Relay:
    """Lines from other ranks to world rank 0, over a private duplicate of ``mpi_comm``
    (collective to create and to :meth:`close`)."""

    def __init__(self, mpi_comm):
        self.t0 = time.monotonic()  # world rank 0's: the clock of every printed line
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
                print(stamp(self.t0, line), file=sys.stderr, flush=True)

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


def stamp(t0, text):
    """A progress line: seconds since ``t0`` (time.monotonic) and the text."""
    return f"[{time.monotonic() - t0:8.1f} s] {text}"


class Progress:
    def __init__(self, comm=None, quiet=False, prefix="", relay=None):
        rank = comm.Get_rank() if comm is not None else 0
        self.enabled = (not quiet) and rank == 0
        self.quiet = quiet
        self.prefix = prefix
        self.relay = relay
        self.t0 = relay.t0 if relay is not None else time.monotonic()

    def __call__(self, msg):
        if not self.enabled:
            return
        text = f"{self.prefix}{msg}"
        if self.relay is not None and self.relay.rank != 0:
            self.relay.send(text)  # stamped by world rank 0 when it prints it
            return
        if self.relay is not None:
            self.relay.drain()
        print(stamp(self.t0, text), file=sys.stderr, flush=True)

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
        last = [time.monotonic()]

        def emit(msg):
            now = time.monotonic()
            if now - last[0] >= interval:
                last[0] = now
                self(msg)

        return emit
