"""Ensemble members over groups of MPI ranks, the one rule ``parjam pack`` and ``parjam run`` share.

The ranks split into min(members, ranks) groups; member m belongs to group m % groups.  With
fewer members than ranks, a group of several ranks shares a member (distributed minimisation,
distributed matrices).
"""

import os

from parjam import env


def member_groups(world, members, todo=None):
    """Split the ranks into min(members, size) groups; member m goes to group m % ngroups.

    Returns (the group's PETSc communicator, this group's members).  ``todo`` (the members still
    to compute on a resumed run) keeps that assignment, so that a member is computed by a group
    of the same size as in an uninterrupted run (bitwise the same packing)."""
    PETSc = env.petsc()
    mpi = world.tompi4py()
    ngroups = min(members, mpi.Get_size())
    color = mpi.Get_rank() * ngroups // mpi.Get_size()
    sub = mpi.Split(color, mpi.Get_rank())
    todo = range(members) if todo is None else todo
    mine = [m for m in todo if m % ngroups == color]
    return PETSc.Comm(sub), mine


class GroupFailures:
    """How groups that work independently end together when one of them fails.

    A group's one-line failure (a ParjamError raised on all of its ranks, e.g. a full disk at a
    member's file or checkpoint) is not seen by the other groups: they would go on to the
    world-wide collectives after their members (gathering the summary rows) and wait there for
    ranks that never come.  So the failed group's ranks :meth:`announce` it to every other
    rank (non-blocking sends on a private communicator), the others look for such a notice
    before each member (:meth:`pending`) and stop, and every rank then calls :meth:`agree`
    (collective over the world): the first failure, in rank order, is raised on every rank, so
    that all end with the same one line and exit status."""

    TAG = 36

    def __init__(self, mpi):
        self.comm = mpi.Dup()
        self.sends = []

    def announce(self, code, message):
        """This rank failed with (exit ``code``, ``message``): tell every other rank."""
        me = self.comm.Get_rank()
        self.sends += [self.comm.isend((code, message), dest=rank, tag=self.TAG)
                       for rank in range(self.comm.Get_size()) if rank != me]

    def pending(self):
        """Whether another group has failed (a notice has arrived)."""
        from mpi4py import MPI

        return bool(self.comm.Iprobe(source=MPI.ANY_SOURCE, tag=self.TAG))

    def agree(self, failure=None, wait=None):
        """Collective: (exit code, message) of the first failed rank, or None; ``failure`` is
        this rank's (code, message), or None.  A failed rank waits at most ``wait`` seconds
        (PARJAM_ERROR_WAIT) for the others: a rank still inside its group's collectives (the
        error was raised on this rank alone, though marked collective) never comes, and then
        a one-rank ParjamError is raised here (the command line aborts every rank)."""
        import time

        import numpy as np
        from mpi4py import MPI

        from parjam.errors import ParjamError

        wait = float(os.environ.get("PARJAM_ERROR_WAIT", "60")) if wait is None else wait
        mine = np.array([0 if failure is None else max(int(failure[0]), 1)], dtype=np.int64)
        codes = np.zeros(self.comm.Get_size(), dtype=np.int64)
        req = self.comm.Iallgather(mine, codes)
        start = time.monotonic()
        while not req.Test():
            if failure is not None and time.monotonic() - start > wait:
                raise ParjamError(f"{failure[1]} (the other ranks did not stop: aborting)",
                                  collective=False)
            time.sleep(0.005)
        me = self.comm.Get_rank()
        messages = {me: failure} if failure is not None else {}
        for rank in np.flatnonzero(codes):  # every failed rank sent each other rank a notice
            if rank != me:
                messages[int(rank)] = self.comm.recv(source=int(rank), tag=self.TAG)
        MPI.Request.Waitall(self.sends)
        self.sends = []
        self.comm.Free()
        return messages[min(messages)] if messages else None
