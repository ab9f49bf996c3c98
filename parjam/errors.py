"""Errors that end a run with a one-line message and a non-zero exit status."""


class ParjamError(Exception):
    """A problem with the user's input or with a result (bad file, unjammed packing, ...).

    Raised identically on every rank when the input is the same everywhere, so that the command
    line can print it once and exit cleanly; anything else on one rank aborts all ranks.
    """

    exit_code = 2

    def __init__(self, message, collective=True):
        super().__init__(message)
        #: raised at the same point on every rank (input validation): exit cleanly; otherwise
        #: the command line aborts all ranks so that none waits forever in a collective call
        self.collective = collective


class UnjammedError(ParjamError):
    """The packing does not jam at the requested density/pressure."""

    exit_code = 3
