"""One module per ``parjam`` subcommand: ``add_parser(subparsers)`` and ``run(args)``; helpers
that several commands share live here (a command never imports another command)."""

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
