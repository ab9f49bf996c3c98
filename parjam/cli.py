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
from parjam.files import petscfiles

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
    for name, command in sub.choices.items():
        command.epilog = exit_codes(name)
    parser.epilog = ("exit status: 0 done, 1 an unexpected failure (a bug: traceback shown), 2 "
                     "bad input or an output that cannot be written (one line, nothing "
                     "written), 3 not jammed, 4 modes: some modes did not converge, 5 run: "
                     "interrupted, 130 interrupted by Ctrl-C; each command's --help lists its "
                     "own")
    return parser


#: exit statuses beyond the common ones (0, 1, 2, 130), per command
EXIT_CODES = {
    "pack": {3: "a member did not jam or its ladder unjammed (its jammed states are written)"},
    "modes": {3: "the packing is not jammed (rattlers only, or too few contacts)",
              4: "some requested modes did not converge to --tol (the converged ones are "
                 "written, the others listed)"},
    "moduli": {3: "the packing is not jammed"},
    "lengths": {3: "the packing is not jammed"},
    "softmodes": {3: "the packing is not jammed"},
    "run": {5: "interrupted: the same command resumes"},
}


def exit_codes(command):
    """The --help epilog of a command: its exit statuses."""
    codes = {0: "done", 2: "bad input, or an output that cannot be written: one line on "
                           "stderr, before any work, nothing written",
             **EXIT_CODES.get(command, {}),
             1: "an unexpected failure (a bug: the traceback is shown)",
             130: "interrupted (Ctrl-C)"}
    return "exit status: " + "; ".join(f"{k} {v}" for k, v in codes.items())


def rank_and_size():
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank(), MPI.COMM_WORLD.Get_size()


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, petsc_args = split_petsc_args(argv)
    # the parser first: --help, --version and a mistyped option end here, before MPI and PETSc
    # start (the command modules load nothing heavy until a command runs)
    parser = build_parser()
    try:
        args = parser.parse_args(ours)
    except SystemExit as exc:  # argparse already printed its help or its one-line usage error
        return int(exc.code or 0)
    try:
        # options files, rc files, PETSC_OPTIONS and PETSc's output files, looked at before
        # PETSc reads them (a FIFO there blocks it, a self-including file crashes it)
        why = petscfiles.startup_problem(petsc_args)
        if why:
            raise ParjamError(why)
        env.init(petsc_args)
    except ParjamError as exc:  # before MPI (or PETSc's start failed): one line, from rank 0
        if launcher_rank() == 0:
            print(f"parjam: error: {one_line(exc)}", file=sys.stderr, flush=True)
        return exc.exit_code
    quiet_closed_stdout()
    rank, size = rank_and_size()
    _outcome_comm()  # collective: made here, while every rank is sure to take part
    petsc_args = options.all_user_args(petsc_args)  # PETSC_OPTIONS: as the command line
    try:
        faults.point("command")  # PARJAM_FAULT testing hook (parjam/faults.py)
        code = _run_command(args, petsc_args)
        # a command is collective: return only when every rank is done, so the files that rank 0
        # wrote exist for whatever any rank does next (e.g. a script or test calling main twice);
        # the closing reduction also tells a rank whether a peer failed with a "collective" error
        # (or could not write its standard output: a full disk behind `> file`)
        mine = _stdout_outcome()
        failed, worst = _closing_outcome(mine)
        _warn_unused_options(petsc_args, args.command, collective=True)
        if failed:
            return worst
        return int(code or 0)
    except ParjamError as exc:
        if rank == 0:
            _warn_unused_options(petsc_args, args.command, collective=False)
        if rank == 0 or not exc.collective:
            prefix = f"[rank {rank}] " if size > 1 and not exc.collective else ""
            print(f"parjam: error: {prefix}{one_line(exc)}", file=sys.stderr, flush=True)
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
        print(f"parjam: error: [rank {rank}] {type(exc).__name__}: {one_line(exc)}",
              file=sys.stderr, flush=True)
        if size > 1:
            _abort(1)
        return 1


def one_line(message):
    """A message on one line: control characters (a newline in a file name) escaped."""
    text = str(message)
    if any(ord(c) < 32 for c in text):
        text = "".join(c if ord(c) >= 32 else repr(c)[1:-1] for c in text)
    return text


def launcher_rank():
    """This process's rank as the MPI launcher set it (before MPI is initialised), 0 if none."""
    for var in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK", "MV2_COMM_WORLD_RANK"):
        text = os.environ.get(var, "")
        if text.isdigit():
            return int(text)
    return 0


def _stdout_outcome():
    """2 if standard output could not be written (the disk behind ``> file`` is full, ``>
    /dev/full``), with one line on this rank; else 0.  Flushes it first."""
    stream = sys.stdout
    if isinstance(stream, _ClosedPipeTolerantStream):
        stream.flush()
        if stream.failure:
            print(f"parjam: error: standard output: cannot write ({stream.failure})",
                  file=sys.stderr, flush=True)
            stream.failure = None
            return ParjamError.exit_code
    return 0


class _ClosedPipeTolerantStream:
    """stdout that goes quiet when its reader goes away (``parjam analyze ... | head -1``): the
    first write or flush that meets a closed pipe sends the rest to /dev/null, so the command
    ends normally on every rank (exit 0) instead of a traceback or a signal dump."""

    def __init__(self, stream):
        self._stream = stream
        self.closed_pipe = False
        self.failure = None  # why a write failed (not a closed pipe): reported at the end

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
        except OSError as exc:  # ENOSPC, EIO, EDQUOT: said once at the end, the rest dropped
            self.failure = self.failure or exc.strerror or str(exc)
            self._quiet()
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._quiet()
        except OSError as exc:
            self.failure = self.failure or exc.strerror or str(exc)
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
    check_inputs(args, petsc_args, PETSc.COMM_WORLD)
    try:
        return args.run(args)
    except PETSc.Error as exc:
        message = options.option_error(exc, petsc_args)
        if message is None:
            raise
        raise ParjamError(message) from None


def check_inputs(args, petsc_args, comm):
    """The input policy (parjam.files.inputs) for the files a command reads, declared by its
    parser as ``reads`` (a function of the arguments giving (option, path) pairs or paths;
    ``reads_directories``: directories are inputs too), before any work, on every rank at once;
    and no file that PETSc's options write (``-log_view :FILE``) may be one of them."""
    from parjam.files import inputs

    reads = getattr(args, "reads", None)
    paths = [p for p in (reads(args) if reads else []) if p is not None]
    inputs.check(comm, paths, directory_ok=getattr(args, "reads_directories", False))
    plain = [p[1] if isinstance(p, tuple) else p for p in paths]
    for option, dest in options.destinations(petsc_args):
        ident = inputs.identity(dest)
        for path in plain:
            if ident is not None and ident == inputs.identity(path):
                # out of the database too: PETSc would still write it at its finalisation
                env.petsc().Options().delValue(option[1:])
                raise ParjamError(f"{option} {inputs.shown(dest)} is the input "
                                  f"{inputs.shown(path)}: refused (PETSc would overwrite it)")


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
