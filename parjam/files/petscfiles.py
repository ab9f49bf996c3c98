"""The files PETSc reads and writes by the user's options, looked at before PETSc starts.

PETSc reads its options (the command line, PETSC_OPTIONS, ``-options_file`` and the rc files)
inside PetscInitialize, before parjam can catch anything: a FIFO there blocks it, a file that
includes itself recurses until the stack overflows (SIGSEGV), a missing or garbage file is an
error dump.  So every file PETSc will read goes through the input policy
(parjam.files.inputs) first, includes are followed and their cycles refused, and every file
PETSc will write (viewers, ``-log_view :FILE``, ``-log_trace``, ``-info``) needs an existing
writable directory (PETSc makes none).  What only PETSc's parser can judge (a garbage line) is
caught by parjam.env around the initialisation and reported as one line.
"""

import os

from parjam import options
from parjam.errors import ParjamError
from parjam.files import inputs

RC_FILES = ("~/.petscrc", ".petscrc", "petscrc")  # read unless -skip_petscrc (PetscOptionsInsert)
MAX_INCLUDE_DEPTH = 16
MAX_OPTIONS_FILE = 1 << 20  # bytes: an options file is a few lines


def file_tokens(path):
    """The option tokens of an options file, loosely (comments after #, aliases skipped): only
    to find the files it includes and the viewers it names; PETSc parses it for real."""
    data = inputs.read_bytes(path, "-options_file", limit=MAX_OPTIONS_FILE)
    tokens = []
    for line in data.decode("utf-8", "replace").splitlines():
        words = line.split("#", 1)[0].split()
        if words and words[0].startswith("-"):
            tokens += words[:2]
    return tokens


def options_files(tokens, depth=0, chain=()):
    """Every options file that ``tokens`` make PETSc read (recursively), each checked by the
    input policy; a file that includes itself (directly or not), or a chain deeper than
    MAX_INCLUDE_DEPTH, is refused.  Returns (files, their tokens)."""
    files, found = [], []
    for name, value in options.pairs(tokens):
        if name not in ("options_file", "options_file_yaml"):
            continue
        if value is None:
            raise ParjamError(f"-{name} needs a file name")
        inputs.require(value, f"-{name}")
        ident = inputs.identity(value)
        if ident in [inputs.identity(c) for c in chain]:
            raise ParjamError(f"-{name} {inputs.shown(value)} includes itself (through "
                              f"{' -> '.join(inputs.shown(c) for c in chain)}): refused")
        if depth >= MAX_INCLUDE_DEPTH:
            raise ParjamError(f"-{name} {inputs.shown(value)}: options files nested more than "
                              f"{MAX_INCLUDE_DEPTH} deep")
        files.append(value)
        if name == "options_file":
            inner = file_tokens(value)
            found += inner
            more, deeper = options_files(inner, depth + 1, chain + (value,))
            files += more
            found += deeper
    return files, found


def rc_files(tokens):
    """The rc files PETSc reads when they exist (unless -skip_petscrc): checked like inputs, a
    FIFO or a device there would block PETSc's start."""
    if any(name == "skip_petscrc" for name, _ in options.pairs(tokens)):
        return []
    out = []
    for name in RC_FILES:
        path = os.path.expanduser(name)
        if inputs.kind(path) != "missing":
            inputs.require(path, "PETSc's rc file")
            out.append(path)
    return out


def destination_problem(option, path):
    """Why PETSc could not write ``path`` (it makes no directory), or None."""
    found = inputs.kind(path)
    name = inputs.shown(path)
    if found not in (None, "missing"):
        return f"{option} {name} is {found}: PETSc cannot write its output there"
    parent = os.path.dirname(os.path.abspath(path))
    if inputs.kind(parent) != "a directory":
        return f"{option} {name}: {inputs.shown(parent)} is not a directory (PETSc makes none)"
    if not os.access(parent, os.W_OK):
        return f"{option} {name}: cannot write in {inputs.shown(parent)}"
    return None


def startup_problem(petsc_args):
    """Everything that would make PETSc's initialisation block, crash or dump, found before it
    runs: options files (and what they include), rc files, PETSC_OPTIONS, output destinations.
    Returns a one-line message or None."""
    tokens = options.all_user_args(petsc_args)
    try:
        _, included = options_files(tokens)
        rc_files(tokens)
        for option, path in options.destinations(tokens + included):
            why = destination_problem(option, path)
            if why:
                return why
    except ParjamError as exc:
        return str(exc)
    return None
