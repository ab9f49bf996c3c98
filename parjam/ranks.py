"""Ensemble members over groups of MPI ranks, the one rule ``parjam pack`` and ``parjam run`` share.

The ranks split into min(members, ranks) groups; member m belongs to group m % groups.  With
fewer members than ranks, a group of several ranks shares a member (distributed minimisation,
distributed matrices).
"""

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
