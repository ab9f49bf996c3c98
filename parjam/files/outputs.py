"""The output policy of every command that writes (docs/explanation/reliability.md, "Outputs").

1. **Checked before any work** (:func:`check`, collective: rank 0 looks, every rank raises the
   same one-line ParjamError): a file can be created in a file output's directory
   (a probe file, so that a read-only mount is caught even for root, who passes every
   permission check); the path is not a directory, not a device, FIFO, socket or other special
   file, and not one of the command's inputs by *file identity* (st_dev, st_ino: a symlink or
   a hard link to an input is the input); two outputs of one command are never the same file.
   A missing directory is made at the write (README's ``--out spectra/NAME``), so the nearest
   existing ancestor must be a directory one can write in.
   A directory output (``pack --out``, ``run --out``, ``plot --img``) is an existing writable
   directory or a name whose parent is one.
2. **Written atomically** (:func:`atomic_path`, :func:`atomic_h5`): into ``.NAME.tmpPID`` in
   the target's directory, fsync'd, then renamed over the target, which the check guaranteed
   to be absent or a regular file (a symlink is followed: the file it names is replaced and the
   link stays).  HDF5 files are built in memory (h5py's core driver) and their image written by
   plain ``os.write``: a full disk or quota is then an OSError of ours, never a failure inside
   the HDF5 library (which left a half-closed file that crashed the interpreter at exit).
3. **A write failure** (ENOSPC, EDQUOT, EROFS, EIO) is one line ``PATH: cannot write (...)``,
   exit status 2, no partial file; :func:`on_root` makes it collective when only rank 0 writes,
   so that every rank ends cleanly (no MPI abort).
"""

import contextlib
import json
import math
import os
import stat
import tempfile

import numpy as np

from parjam.errors import ParjamError


def same_file(a, b):
    """Whether two existing paths name the same file (after symlinks), by (st_dev, st_ino)."""
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return False
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def target(path):
    """The path a write really replaces: a symlink's final target (the link itself stays)."""
    return os.path.realpath(os.fspath(path))


def _special(mode):
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _kind(mode):
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "a special file"


def _probe(directory):
    """None if a file can be created in ``directory``, else the reason (errno text)."""
    try:
        fd, name = tempfile.mkstemp(prefix=".parjam-probe-", dir=directory)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.remove(name)
    return None


def file_problem(path, option="--out"):
    """Why a file cannot be written at ``path`` (a one-line text), or None."""
    path = os.fspath(path)
    if not path:
        return f"{option}: empty file name"
    real = target(path)
    try:
        st = os.stat(real)
    except FileNotFoundError:
        st = None
    except NotADirectoryError:
        return f"{option} {path}: {os.path.dirname(path)} is not a directory"
    except OSError as exc:
        return f"{option} {path}: cannot examine ({exc.strerror})"
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            return f"{option} {path} is a directory"
        if _special(st.st_mode):
            return f"{option} {path} is {_kind(st.st_mode)}, not a regular file: refused"
    directory = os.path.dirname(real)  # made at the write with its missing parents: the
    while not os.path.exists(directory):  # nearest existing ancestor must be writable
        directory = os.path.dirname(directory)
    if not os.path.isdir(directory):
        return f"{option} {path}: {directory} is not a directory"
    why = _probe(directory)
    if why:
        return f"{option} {path}: cannot write in {directory} ({why})"
    return None


def dir_problem(path, option="--out"):
    """Why ``path`` cannot be (made into) an output directory, or None."""
    path = os.fspath(path)
    if not path:
        return f"{option}: empty directory name"
    real = target(path)
    if os.path.exists(real):
        if not os.path.isdir(real):
            return f"{option} {path} exists and is not a directory"
        why = _probe(real)
        return f"{option} {path}: cannot write in it ({why})" if why else None
    parent = os.path.dirname(real)  # made with its missing parents: the nearest existing
    while not os.path.exists(parent):  # ancestor must be a writable directory
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        return f"{option} {path}: {parent} is not a directory"
    why = _probe(parent)
    return f"{option} {path}: cannot create it ({why})" if why else None


MAX_TREE_ENTRIES = 10_000_000  # a directory output larger than this is not looked through


def tree_problems(option, root, owned, inputs=()):
    """Problems of the entries parjam writes inside an existing directory output ``root``:
    ``owned(relative path)`` says "file", "dir" or None (not parjam's: left alone, not looked
    into).  An owned entry must be absent or what parjam makes there: not a symlink (parjam
    makes none, and writing through one would replace the file it names, an input say), not a
    FIFO or device (reading it blocks), not a file where a directory belongs or the reverse,
    and not one of the ``inputs`` by identity (a hard link)."""
    root = os.fspath(root)
    if not os.path.isdir(root):
        return []
    idents = {}
    for inp in inputs:
        try:
            st = os.stat(inp)
            idents[(st.st_dev, st.st_ino)] = inp
        except OSError:
            pass
    out, seen = [], 0
    stack = [""]
    while stack and not out:
        rel_dir = stack.pop()
        try:
            names = sorted(os.listdir(os.path.join(root, rel_dir)))
        except OSError:
            continue
        for name in names:
            seen += 1
            if seen > MAX_TREE_ENTRIES:
                return out
            rel = os.path.join(rel_dir, name)
            want = owned(rel)
            if want is None:
                continue
            why = _entry_problem(os.path.join(root, rel), want, idents)
            if why:
                out.append(f"{option} {root}: {rel} {why}: refused (parjam writes its own files "
                           f"there; remove or rename it)")
                break
            if want == "dir" and os.path.isdir(os.path.join(root, rel)):
                stack.append(rel)
    return out


def _entry_problem(path, want, idents):
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if stat.S_ISLNK(st.st_mode):
        return f"is a symlink (to {os.readlink(path)})"
    if stat.S_ISDIR(st.st_mode):
        return None if want == "dir" else "is a directory"
    if not stat.S_ISREG(st.st_mode):
        return f"is {_kind(st.st_mode)}"
    if want == "dir":
        return "is a file where parjam keeps a directory"
    if (st.st_dev, st.st_ino) in idents:
        return f"is the input {idents[(st.st_dev, st.st_ino)]}"
    return None


def problems(files=(), dirs=(), inputs=(), trees=()):
    """Every problem of a command's outputs: ``files`` and ``dirs`` are (option, path) pairs
    (path None: not asked for), ``inputs`` the paths the command reads, ``trees`` (option,
    directory, owned) of directory outputs whose entries parjam writes (:func:`tree_problems`)."""
    files = [(o, os.fspath(p)) for o, p in files if p is not None]
    dirs = [(o, os.fspath(p)) for o, p in dirs if p is not None]
    out = []
    for option, path in files:
        why = file_problem(path, option)
        if why:
            out.append(why)
    for option, path in dirs:
        why = dir_problem(path, option)
        if why:
            out.append(why)
    for option, path in files + dirs:
        for inp in inputs:
            if same_file(path, inp) or target(path) == target(inp):
                out.append(f"{option} {path} is the input {inp}: refused (it would be "
                           f"destroyed)")
                break
    seen = {}
    for option, path in files:
        key = target(path)
        if key in seen or any(same_file(path, p) for p in seen.values()):
            out.append(f"{option} {path} names the same file as another output")
        seen[key] = path
    if not out:
        for option, root, owned in trees:
            out += tree_problems(option, root, owned, inputs)
    return out


def check(comm=None, files=(), dirs=(), inputs=(), trees=()):
    """Refuse bad outputs before any work, on every rank at once (one line, exit 2).  ``comm``
    is an mpi4py or petsc4py communicator (None: this process alone); rank 0 looks."""
    mpi = _mpi(comm)
    found = problems(files, dirs, inputs, trees) if mpi is None or mpi.Get_rank() == 0 else None
    if mpi is not None and mpi.Get_size() > 1:
        found = mpi.bcast(found, root=0)
    if found:
        raise ParjamError(found[0])


def _mpi(comm):
    if comm is None:
        return None
    return comm.tompi4py() if hasattr(comm, "tompi4py") else comm


def on_root(comm, write):
    """Call ``write()`` on rank 0 only; a ParjamError there (a failed write) is raised on every
    rank, so that all end with the same one line instead of an MPI abort."""
    mpi = _mpi(comm)
    rank = 0 if mpi is None else mpi.Get_rank()
    message, result = None, None
    if rank == 0:
        try:
            result = write()
        except ParjamError as exc:
            message = str(exc)
    if mpi is not None and mpi.Get_size() > 1:
        message = mpi.bcast(message, root=0)
    if message:
        raise ParjamError(message)
    return result


def temporary_name(path, pid=None):
    """``.NAME.tmpPID`` beside the file a write of ``path`` replaces (pack's stale-file cleanup
    and SIGTERM handler know the pattern)."""
    real = target(path)
    return os.path.join(os.path.dirname(real),
                        f".{os.path.basename(real)}.tmp{os.getpid() if pid is None else pid}")


def _fail(path, exc):
    return ParjamError(f"{path}: cannot write ({exc.strerror or exc})", collective=False)


@contextlib.contextmanager
def atomic_path(path, suffix="", make_dirs=True):
    """Yield a temporary path to write ``path`` to; on success it is fsync'd and renamed over
    ``path`` (refused if ``path`` became a directory or a special file meanwhile); on failure
    it is removed.  An OSError becomes ``PATH: cannot write (...)`` (not collective: use
    :func:`on_root` when only one rank writes)."""
    path = os.fspath(path)
    real = target(path)
    tmp = temporary_name(path) + suffix
    try:
        if make_dirs:
            os.makedirs(os.path.dirname(real), exist_ok=True)
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        _still_replaceable(path, real)
        os.replace(tmp, real)
    except OSError as exc:
        raise _fail(path, exc) from None
    finally:
        for leftover in (tmp, f"{tmp}.tmp{os.getpid()}"):  # also a writer's own temporary
            with contextlib.suppress(OSError):
                os.remove(leftover)


def _still_replaceable(path, real):
    """The check of :func:`file_problem` again just before the rename (the path may have been
    replaced by a directory or a device while the command worked)."""
    try:
        mode = os.stat(real).st_mode
    except FileNotFoundError:
        return
    if stat.S_ISDIR(mode) or _special(mode):
        raise ParjamError(f"{path} became {'a directory' if stat.S_ISDIR(mode) else _kind(mode)} "
                          f"while parjam worked: not replaced", collective=False)


def write_bytes(path, data, make_dirs=True):
    """``data`` to ``path`` atomically (policy above)."""
    with atomic_path(path, make_dirs=make_dirs) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)


_IMAGES = 0


@contextlib.contextmanager
def atomic_h5(path, make_dirs=True):
    """An h5py File in memory; its image goes to ``path`` atomically when the block succeeds.

    The core driver keeps every write inside memory: the disk sees only our own ``os.write``
    of the finished image, so a full disk is a clean one-line error and HDF5 never holds a
    half-written file open until the interpreter exits."""
    global _IMAGES
    _IMAGES += 1
    import h5py  # here: the command line loads this module before any file is written

    f = h5py.File(f"parjam-image-{os.getpid()}-{_IMAGES}.h5", "w", driver="core",
                  backing_store=False)
    try:
        yield f
        f.flush()
        image = f.id.get_file_image()
    finally:
        f.close()
    write_bytes(path, image, make_dirs=make_dirs)


def plain(value):
    """``value`` with numpy scalars and arrays as Python numbers and lists, and every NaN or
    infinity as None: JSON has no NaN (Python's json writes the invalid token ``NaN``)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_text(value, **kw):
    """Valid JSON of ``value`` (see :func:`plain`): never NaN or Infinity."""
    return json.dumps(plain(value), allow_nan=False, **kw)


def remove_partial(path):
    """Remove this process's temporary file of ``path`` (if a writer failed outside
    :func:`atomic_path`)."""
    with contextlib.suppress(OSError):
        os.remove(temporary_name(path))
