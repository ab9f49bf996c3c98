"""The ``parjam`` command line: ``parjam <command> [options] [-petsc_option value ...]``.

Each command lives in its own module under :mod:`parjam.commands` with ``add_parser(sub)``
and ``run(args)``; they are discovered automatically.  Arguments that look like PETSc options
(``-log_view``, ``-eps_nev 10``, ``-st_pc_type cholesky``; a single dash and a name of two or
more characters) go to PETSc's options database before any PETSc object is created.
"""

import argparse
import contextlib
import importlib
import os
import pkgutil
import re
import signal
import sys
import time
import traceback

import numpy as np

from parjam import __version__, env, faults, options
from parjam.errors import ParjamError

_PETSC_OPT = re.compile(r"^-[A-Za-z_][A-Za-z0-9_:]+$")
_NUMBER = re.compile(r"^-?[0-9.]")


def split_petsc_args(argv):
    """Separate PETSc options (and their values) from parjam's own arguments."""
    ours, petsc = [], []
    k = 0
    while k < len(argv):
        tok = argv[k]
        if _PETSC_OPT.match(tok):
            petsc.append(tok)
            nxt = argv[k + 1] if k + 1 < len(argv) else None
            if nxt is not None and (not nxt.startswith("-") or _NUMBER.match(nxt)):
                petsc.append(nxt)
                k += 1
        else:
            ours.append(tok)
        k += 1
    return ours, petsc


class OneLineParser(argparse.ArgumentParser):
    """argparse with a one-line error (``parjam: error: ...``) instead of usage + message; the
    subcommand parsers inherit it."""

    def error(self, message):
        self.exit(2, f"parjam: error: {message} (see {self.prog} --help)\n")


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Every option's default in --help, unless its help already states it (as argparse's
    ArgumentDefaultsHelpFormatter, without repeating "(default 3)" or "(1.4)")."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if (default is None or default is False or default is argparse.SUPPRESS
                or (isinstance(default, (list, tuple)) and not default)  # no "(default: )"
                or action.option_strings == [] or "%(default)" in text):
            return text
        shown = " ".join(str(v) for v in default) if isinstance(default, (list, tuple)) \
            else str(default)
        if "default" in text or f"({shown})" in text:
            return text
        return f"{text} (default: {shown})"


class CommandParser(OneLineParser):
    """The parsers of the commands: one-line errors, defaults shown in --help."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser():
    import parjam.commands as pkg

    parser = OneLineParser(
        prog="parjam",
        description="Parallel vibrational analysis of jammed soft-sphere packings "
        "(Wyart, Silbert, Nagel & Witten, PRE 72, 051306). PETSc/SLEPc options may follow, "
        "with the prefix of the solver they are for (-modes_eps_*, -modes_st_*, -newton_ksp_*, "
        "-moduli_ksp_*, -soft_*; global ones such as -log_view without); an option that no "
        "solver read is reported at the end with the nearest valid name.",
    )
    parser.add_argument("--version", action="version", version=f"parjam {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=CommandParser)
    sub.required = True
    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        importlib.import_module(f"parjam.commands.{mod}").add_parser(sub)
    return parser


def rank_and_size():
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank(), MPI.COMM_WORLD.Get_size()


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, petsc_args = split_petsc_args(argv)
    try:
        env.init(petsc_args)
    except ParjamError as exc:  # a broken PETSC_DIR/SLEPC_DIR: before MPI, one line
        print(f"parjam: error: {exc}", file=sys.stderr, flush=True)
        return exc.exit_code
    quiet_closed_stdout()
    rank, size = rank_and_size()
    _outcome_comm()  # collective: made here, while every rank is sure to take part
    parser = build_parser()
    try:
        args = parser.parse_args(ours)
    except SystemExit as exc:  # argparse already printed its one-line usage error
        return int(exc.code or 0)
    try:
        faults.point("command")  # PARJAM_FAULT testing hook (parjam/faults.py)
        code = _run_command(args, petsc_args)
        # a command is collective: return only when every rank is done, so the files that rank 0
        # wrote exist for whatever any rank does next (e.g. a script or test calling main twice);
        # the closing reduction also tells a rank whether a peer failed with a "collective" error
        failed, worst = _closing_outcome(0)
        _warn_unused_options(petsc_args, args.command, collective=True)
        if failed:
            return worst
        return int(code or 0)
    except ParjamError as exc:
        if rank == 0:
            _warn_unused_options(petsc_args, args.command, collective=False)
        if rank == 0 or not exc.collective:
            prefix = f"[rank {rank}] " if size > 1 and not exc.collective else ""
            print(f"parjam: error: {prefix}{exc}", file=sys.stderr, flush=True)
        if size > 1 and not exc.collective:
            _abort(exc.exit_code)
        if size > 1 and not _ended_together(exc):
            _abort(exc.exit_code)
        return exc.exit_code
    except KeyboardInterrupt:
        print("parjam: interrupted", file=sys.stderr, flush=True)
        if size > 1:
            _abort(130)
        return 130
    except Exception as exc:  # a bug or an unexpected failure: show it, end every rank
        traceback.print_exc()
        print(f"parjam: error: [rank {rank}] {type(exc).__name__}: {exc}", file=sys.stderr,
              flush=True)
        if size > 1:
            _abort(1)
        return 1


class _ClosedPipeTolerantStream:
    """stdout that goes quiet when its reader goes away (``parjam analyze ... | head -1``): the
    first write or flush that meets a closed pipe sends the rest to /dev/null, so the command
    ends normally on every rank (exit 0) instead of a traceback or a signal dump."""

    def __init__(self, stream):
        self._stream = stream
        self.closed_pipe = False

    def _quiet(self):
        self.closed_pipe = True
        devnull = os.open(os.devnull, os.O_WRONLY)
        with contextlib.suppress(OSError, ValueError):
            os.dup2(devnull, self._stream.fileno())
        os.close(devnull)

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._quiet()
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._quiet()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def quiet_closed_stdout():
    """SIGPIPE ignored again after PETSc installed its handler (which dumps 'Caught signal
    number 13' and aborts), and a stdout that tolerates a closed pipe."""
    if hasattr(signal, "SIGPIPE"):
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    if not isinstance(sys.stdout, _ClosedPipeTolerantStream) and sys.stdout is not None:
        sys.stdout = _ClosedPipeTolerantStream(sys.stdout)


def _run_command(args, petsc_args):
    """The command; a PETSc error that a bad option value caused becomes a one-line ParjamError
    (parjam.options.option_error)."""
    PETSc = env.petsc()
    try:
        return args.run(args)
    except PETSc.Error as exc:
        message = options.option_error(exc, petsc_args)
        if message is None:
            raise
        raise ParjamError(message) from None


def _warn_unused_options(petsc_args, command, collective):
    """One warning line per option given that no solver read (on any rank, when
    ``collective``), on rank 0 (parjam.options.warnings_for)."""
    if not petsc_args:
        return

    lines = options.warnings_for(petsc_args, command)
    if collective and _outcome_comm().Get_size() > 1:
        # an option is unused only if no rank read it
        sets = _outcome_comm().allgather(set(lines))
        lines = [ln for ln in lines if all(ln in other for other in sets)]
    if _outcome_comm().Get_rank() == 0:
        for line in lines:
            print(f"parjam: warning: {line}", file=sys.stderr, flush=True)


_OUTCOME_COMM = None
ERROR_WAIT = float(os.environ.get("PARJAM_ERROR_WAIT", "60"))  # seconds


def _outcome_comm():
    """A private duplicate of COMM_WORLD for the closing reduction (it can never match a
    collective of a command)."""
    global _OUTCOME_COMM
    if _OUTCOME_COMM is None:
        from mpi4py import MPI

        _OUTCOME_COMM = MPI.COMM_WORLD.Dup()
    return _OUTCOME_COMM


def _closing_outcome(code, wait=None):
    """Sum of failed ranks and the largest exit code over all ranks, by a reduction on the
    private communicator; with ``wait`` (seconds), give up and return None if the other ranks
    do not join in time (they are stuck in a collective of the command)."""
    from mpi4py import MPI

    comm = _outcome_comm()
    if comm.Get_size() == 1:
        return int(code != 0), code
    mine = np.array([int(code != 0), code], dtype=np.int64)
    total, worst = np.zeros(2, dtype=np.int64), np.zeros(2, dtype=np.int64)
    reqs = [comm.Iallreduce(mine, total, op=MPI.SUM), comm.Iallreduce(mine, worst, op=MPI.MAX)]
    start = time.monotonic()
    while not MPI.Request.Testall(reqs):
        if wait is not None and time.monotonic() - start > wait:
            return None
        time.sleep(0.005)
    return int(total[0]), int(worst[1])


def _ended_together(exc):
    """A ParjamError marked collective is normally raised on every rank at once.  If some ranks
    did not raise it, they are either finishing the command (and learn here that a peer failed)
    or stuck in one of its collectives, waiting for this rank: then end the job (MPI Abort)
    after PARJAM_ERROR_WAIT seconds instead of hanging."""
    from mpi4py import MPI

    outcome = _closing_outcome(exc.exit_code or 1, wait=ERROR_WAIT)
    if outcome is None:
        rank = MPI.COMM_WORLD.Get_rank()
        print(f"parjam: error: [rank {rank}] {exc} (the other ranks did not end the command: "
              f"aborting)", file=sys.stderr, flush=True)
        return False
    failed, _ = outcome
    if failed < MPI.COMM_WORLD.Get_size() and MPI.COMM_WORLD.Get_rank() != 0:
        print(f"parjam: error: [rank {MPI.COMM_WORLD.Get_rank()}] {exc}", file=sys.stderr,
              flush=True)
    return True


def _abort(code):
    from mpi4py import MPI

    MPI.COMM_WORLD.Abort(code)


def entry():
    sys.exit(main())
