"""Deliberate faults, to test that a failure on one MPI rank ends every rank (docs/explanation/reliability.md).

``PARJAM_FAULT=POINT@RANK[:KIND]`` makes world rank RANK fail when it reaches the named POINT:

- POINT: ``command`` (in ``parjam.cli.main``, just before any command runs), ``pack.member``
  (in ``parjam pack``, after a member's files and manifest record are written) or
  ``pack.checkpoint`` (after a member's checkpoint is written, parjam.files.checkpoint);
- KIND: ``error`` (default: a non-collective ParjamError, the path of a problem only one rank
  sees), ``crash`` (a RuntimeError, the path of a bug) or ``kill`` (the process SIGKILLs itself,
  as the out-of-memory killer would) or ``collective`` (a ParjamError marked collective although
  only this rank raises it: a mislabelled error, which must not hang the other ranks).

Only this module reads the variable; unset (the normal case) it costs one dictionary look-up.
"""

import os
import signal

from parjam.errors import ParjamError

POINTS = ("command", "pack.member", "pack.checkpoint")
KINDS = ("error", "crash", "kill", "collective")


class InjectedCrash(RuntimeError):
    """A simulated bug (PARJAM_FAULT kind ``crash``)."""


def parse(text):
    """``"pack.member@1:kill"`` -> ("pack.member", 1, "kill"); ParjamError if malformed."""
    where, _, kind = text.partition(":")
    point, _, rank = where.partition("@")
    kind = kind or "error"
    if point not in POINTS or kind not in KINDS or not rank.isdigit():
        raise ParjamError(f"PARJAM_FAULT={text!r}: expected POINT@RANK[:KIND] with POINT in "
                          f"{', '.join(POINTS)} and KIND in {', '.join(KINDS)}")
    return point, int(rank), kind


def point(name):
    """Fail here if PARJAM_FAULT names this point and this world rank."""
    text = os.environ.get("PARJAM_FAULT")
    if not text:
        return
    where, rank, kind = parse(text)
    if where != name:
        return
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() != rank:
        return
    if kind == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if kind == "collective":
        raise ParjamError(f"injected collective error at {name} (PARJAM_FAULT)")
    if kind == "crash":
        raise InjectedCrash(f"injected crash at {name} (PARJAM_FAULT)")
    raise ParjamError(f"injected error at {name} (PARJAM_FAULT)", collective=False)
