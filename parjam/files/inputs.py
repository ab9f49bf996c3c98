"""The input policy of every command that reads (beside parjam.files.outputs, the output policy;
docs/results/hostile.md lists the cases it answers).

1. **Looked at before it is opened** (:func:`problem`, :func:`check`, collective like
   outputs.check: rank 0 looks, every rank raises the same one-line ParjamError): an input is
   an existing regular file (or, where a command reads directories, a directory).  Anything else
   is named for what it is -- missing, a directory, a FIFO, a character or block device, a
   socket, a symlink loop, a dangling symlink, below a file, unreadable -- and refused before
   any ``open``: a FIFO opened for reading blocks until a writer appears, a device streams
   forever.
2. **Opened without blocking** (:func:`open_file`): ``O_NONBLOCK`` for the open itself, then
   ``fstat`` of the descriptor: a path that became a FIFO or a device after the check is still
   refused, never read.
3. **Names built from user text** (scene, system and member names) are one path component
   (:func:`component`): every character outside ``A-Z a-z 0-9 . _ + = , -`` becomes ``_``, a
   leading dot or dash too (no hidden files, nothing read as an option), so ``../../X``,
   ``/abs/dir`` and ``a/b`` stay inside the output root; :func:`inside` checks a joined path
   is there.  Two names that give one file name (also on a case-insensitive file system) are
   refused by :func:`distinct` before any work.
4. **Identity**: :func:`identity` is (st_dev, st_ino) after symlinks; outputs.check refuses an
   output that is one of the inputs by it, so a symlink or a hard link to an input is the input.
"""

import errno
import fcntl
import os
import re
import stat

from parjam.errors import ParjamError

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def shown(path):
    """A path as it can appear in a one-line message: control characters (a newline in a file
    name) escaped."""
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if any(ord(c) < 32 or ord(c) == 127 for c in text):
        return repr(text)[1:-1]
    return text


def kind(path):
    """What ``path`` is, in words: None for a regular file, else 'missing', 'a directory',
    'a FIFO', 'a character device', 'a block device', 'a socket', 'a symlink loop',
    'a dangling symlink to X', 'below a file that is not a directory', 'not accessible (...)'."""
    path = os.fspath(path)
    if not path:
        return "an empty name"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        try:
            if stat.S_ISLNK(os.lstat(path).st_mode):
                return f"a dangling symlink to {shown(os.readlink(path))}"
        except OSError:
            pass
        return "missing"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "a symlink loop"
        if exc.errno == errno.ENOTDIR:
            return "below a file that is not a directory"
        if exc.errno == errno.ENAMETOOLONG:
            return "a name too long for the file system"
        return f"not accessible ({exc.strerror or exc})"
    except ValueError:  # a NUL byte in the name
        return "a name with a NUL character"
    for test, name in _KINDS:
        if test(st.st_mode):
            return name
    if not stat.S_ISREG(st.st_mode):
        return "a special file"
    return None


def problem(path, what=None, directory_ok=False):
    """Why ``path`` cannot be read as an input (one line, starting with ``what``, e.g. the
    option, then the path), or None."""
    if path is None:
        return None
    found = kind(path)
    name = f"{what} {shown(path)}" if what else shown(path)
    if found == "missing":
        return f"{name}: no such file" + " or directory" * directory_ok
    if found == "a directory":
        if directory_ok:
            return None if os.access(path, os.R_OK | os.X_OK) else \
                f"{name}: directory not readable (permission denied)"
        return f"{name} is a directory, not a file"
    if found is not None:
        blocks = " (reading it would block)" if found in ("a FIFO", "a socket") else ""
        return f"{name} is {found}, not a regular file: refused{blocks}"
    if not os.access(path, os.R_OK):
        return f"{name}: not readable (permission denied)"
    return None


def require(path, what=None, directory_ok=False):
    """Raise the one-line ParjamError of :func:`problem` (this rank alone)."""
    why = problem(path, what, directory_ok)
    if why:
        raise ParjamError(why)


def problems(paths, directory_ok=False):
    """Every problem of ``paths``: (what, path) pairs or plain paths (path None: not given)."""
    out = []
    for item in paths:
        what, path = item if isinstance(item, tuple) else (None, item)
        why = problem(path, what, directory_ok)
        if why:
            out.append(why)
    return out


def check(comm, paths, directory_ok=False):
    """Refuse bad inputs before any work, on every rank at once (one line, exit 2); rank 0 of
    ``comm`` (mpi4py or petsc4py, None: this process) looks."""
    mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    found = problems(paths, directory_ok) if mpi is None or mpi.Get_rank() == 0 else None
    if mpi is not None and mpi.Get_size() > 1:
        found = mpi.bcast(found, root=0)
    if found:
        raise ParjamError(found[0])


def open_file(path, mode="rb", what=None, **kw):
    """``open(path, mode)`` for reading that never blocks on a FIFO or reads a device: the
    descriptor is opened with O_NONBLOCK, checked to be a regular file, then made blocking."""
    why = problem(path, what)
    if why:
        raise ParjamError(why)
    name = f"{what} {shown(path)}" if what else shown(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except OSError as exc:
        raise ParjamError(f"{name}: cannot open ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ParjamError(f"{name} became {_mode_kind(st.st_mode)} while parjam looked: "
                              f"refused")
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~os.O_NONBLOCK)
        return os.fdopen(fd, mode, **kw)
    except BaseException:
        os.close(fd)
        raise


def _mode_kind(mode):
    for test, name in _KINDS:
        if test(mode):
            return name
    return "a special file"


def read_bytes(path, what=None, limit=None):
    """The bytes of a regular file (:func:`open_file`); ``limit``: refuse larger files."""
    with open_file(path, "rb", what) as fh:
        if limit is not None and os.fstat(fh.fileno()).st_size > limit:
            raise ParjamError(f"{what + ' ' if what else ''}{shown(path)}: larger than {limit} "
                              f"bytes: refused")
        return fh.read()


def identity(path):
    """(st_dev, st_ino) of the file ``path`` names after symlinks, or None."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


# --------------------------------------------------------------------------- names from user text

_UNSAFE = re.compile(r"[^A-Za-z0-9._+=,-]")
_LEADING = re.compile(r"^[.-]+")
MAX_COMPONENT = 100  # bytes; the stage and summary names add ~40 to it (file systems: 255)


def component(text, what="name"):
    """``text`` as one safe path component (see the module doc); a ParjamError if nothing of
    it is left."""
    if not isinstance(text, str):
        raise ParjamError(f"{what} must be a string, got {type(text).__name__}")
    safe = _UNSAFE.sub("_", text)
    safe = _LEADING.sub(lambda m: "_" * len(m.group()), safe)
    if not safe.strip("_"):
        raise ParjamError(f"{what} {shown(text)!r} gives no usable file name (letters, digits, "
                          f". _ + = , - are kept)")
    if len(safe) > MAX_COMPONENT:
        raise ParjamError(f"{what} is {len(safe)} characters long: at most {MAX_COMPONENT} "
                          f"(it names files and directories)")
    return safe


def distinct(names, what="names"):
    """Refuse two different labels that give one file name: ``names`` maps each label to its
    file name; names equal up to case collide too (case-insensitive file systems)."""
    seen = {}
    for label, name in names.items():
        key = name.casefold()
        if key in seen and seen[key] != label:
            raise ParjamError(f"{what} {shown(str(seen[key]))!r} and {shown(str(label))!r} give "
                              f"the same file name {shown(name)!r}: make them differ")
        seen[key] = label


def inside(root, *parts):
    """``root`` joined with ``parts``, refused unless it stays under ``root`` (after '..')."""
    path = os.path.join(root, *parts)
    base = os.path.abspath(root)
    if os.path.commonpath([base, os.path.abspath(path)]) != base:
        raise ParjamError(f"{shown(path)} would lie outside {shown(root)}: refused")
    return path
