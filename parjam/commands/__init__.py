"""One module per ``parjam`` subcommand: ``add_parser(subparsers)`` and ``run(args)``; helpers
that several commands share live here (a command never imports another command).

Why a command imports its work inside ``run``: the command line imports every command module to
build its parser, before PETSc is initialised with the user's options (parjam.env), so a module
level import of the physics and solver modules would cost every ``parjam`` call (``--help``
included) their start-up (0.6 s measured for one command's imports of scipy.linalg and h5py).
mpi4py is imported inside functions everywhere for the same start-up order."""

import numpy as np

from parjam.errors import ParjamError


def parse_pair(text, name):
    """'A,B' -> (A, B) floats, or a one-line error."""
    try:
        a, b = (float(x) for x in text.split(","))
    except (ValueError, AttributeError):
        raise ParjamError(f"{name} must be two numbers A,B, got {text!r}") from None
    if not (np.isfinite(a) and np.isfinite(b)):
        raise ParjamError(f"{name} must be finite, got {text!r}")
    return a, b
