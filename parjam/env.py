"""The one place where PETSc and SLEPc are located and initialised.

HPC users bring their own PETSc/SLEPc (>= 3.18) through PETSC_DIR/PETSC_ARCH and SLEPC_DIR;
when those are unset and Debian's packages are installed, their paths are used.  Every
command-line argument that starts with ``-`` after parjam's own options reaches PETSc's options
database, so ``-log_view``, ``-eps_*``, ``-st_*`` and ``-ksp_*`` configure the solvers.
"""

import contextlib
import functools
import os
import sys
import tempfile

DEBIAN_PETSC_DIR = "/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real"
DEBIAN_SLEPC_DIR = "/usr/lib/slepcdir/slepc3.18/x86_64-linux-gnu-real"

_initialised = False


def _default_dirs():
    """Fill PETSC_DIR/SLEPC_DIR with Debian's paths only when the user set nothing, and put the
    petsc4py/slepc4py that belong to those installations on sys.path (Debian installs them under
    $PETSC_DIR/lib/python3/dist-packages, source builds under $PETSC_DIR/$PETSC_ARCH/lib)."""
    if "PETSC_DIR" not in os.environ and os.path.isdir(DEBIAN_PETSC_DIR):
        os.environ["PETSC_DIR"] = DEBIAN_PETSC_DIR
    if "SLEPC_DIR" not in os.environ and os.path.isdir(DEBIAN_SLEPC_DIR):
        os.environ["SLEPC_DIR"] = DEBIAN_SLEPC_DIR
    arch = os.environ.get("PETSC_ARCH", "")
    for var in ("PETSC_DIR", "SLEPC_DIR"):
        root = os.environ.get(var)
        if not root:
            continue
        for sub in ("lib/python3/dist-packages", os.path.join(arch, "lib")):
            path = os.path.join(root, sub)
            if os.path.isdir(path) and path not in sys.path:
                sys.path.append(path)


def check_dirs(missing=None):
    """A one-line diagnosis of PETSC_DIR / SLEPC_DIR as set by the user, or None: each must be
    an existing directory, and the one whose bindings (``missing``: petsc4py or slepc4py)
    could not be imported is named with the places that were searched."""
    arch = os.environ.get("PETSC_ARCH", "")
    for var, module in (("PETSC_DIR", "petsc4py"), ("SLEPC_DIR", "slepc4py")):
        root = os.environ.get(var)
        if root is None:
            continue
        if not root:
            return f"{var} is set but empty: unset it or point it at an installation"
        if not os.path.isdir(root):
            return f"{var}={root} is not a directory: unset it or point it at an installation"
        if missing == module:
            places = " and ".join(os.path.join(root, sub) for sub in (
                "lib/python3/dist-packages", os.path.join(arch, "lib") if arch else "lib"))
            return f"{var}={root} holds no {module} (looked in {places})"
    return None


def init(petsc_args=None):
    """Initialise petsc4py and slepc4py once, passing ``petsc_args`` to the options database.
    A broken PETSC_DIR/SLEPC_DIR or missing bindings are one-line ParjamErrors."""
    global _initialised
    if not _initialised:
        _default_dirs()
        try:
            import petsc4py
            import slepc4py
        except ImportError as exc:
            why = check_dirs(exc.name)
            from parjam.errors import ParjamError

            raise ParjamError(f"cannot import {exc.name or 'petsc4py/slepc4py'}: "
                              f"{why or 'install petsc4py and slepc4py (see README.md)'}") \
                from None
        args = [sys.argv[0]] + list(petsc_args or [])
        with _stderr_captured() as captured:
            try:
                petsc4py.init(args)
                slepc4py.init(args)
                from petsc4py import PETSc  # noqa: F401  (PetscInitialize runs here)
                failure = None
            except Exception as exc:  # PETSc.Error: an options file PETSc's parser refused
                failure = exc
        if failure is not None:
            from parjam.errors import ParjamError

            raise ParjamError(f"PETSc did not start: {startup_message(captured.text, failure)}")
        sys.stderr.write(captured.text)  # what MPI or PETSc said while starting, as it was
        sys.stderr.flush()
        _initialised = True
    from petsc4py import PETSc

    return PETSc


class _Captured:
    text = ""


@contextlib.contextmanager
def _stderr_captured():
    """File descriptor 2 redirected to a temporary file (PETSc's C code writes its error dump
    there, not through Python); its text is in ``.text`` afterwards."""
    captured = _Captured()
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            captured.text = tmp.read().decode("utf-8", "replace")


def startup_message(dump, exc):
    """The one line of a PETSc error dump: the message after the error class (``Unknown first
    token in options file F line 1: garbage``), else the error code."""
    lines = [ln.split("PETSC ERROR:", 1)[1].strip() for ln in dump.splitlines()
             if "PETSC ERROR:" in ln]
    lines = [ln for ln in lines if ln and not ln.startswith(("---", "See ", "Petsc Release",
                                                             "#", "Configure options"))
             and " on a " not in ln]
    if len(lines) >= 2:
        return f"{lines[1]} ({lines[0].lower()})"
    if lines:
        return lines[0]
    return f"error code {getattr(exc, 'ierr', exc)}"


def petsc():
    """The PETSc module, initialised (without extra options if nobody initialised it yet)."""
    return init()


def slepc():
    init()
    from slepc4py import SLEPc

    return SLEPc


def mpi_comm():
    """mpi4py's COMM_WORLD (PETSc initialised first so both agree on MPI)."""
    init()
    from mpi4py import MPI

    return MPI.COMM_WORLD


@functools.lru_cache(maxsize=None)
def has_mumps():
    """Whether the PETSc build offers MUMPS as a factorisation package."""
    PETSc = init()
    A = PETSc.Mat().createAIJ([2, 2], nnz=1, comm=PETSc.COMM_SELF)
    A.setValue(0, 0, 1.0)
    A.setValue(1, 1, 1.0)
    A.assemble()
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    pc.setOperators(A)
    pc.setType("cholesky")
    try:
        pc.setFactorSolverType("mumps")
        pc.setUp()
        ok = True
    except PETSc.Error:
        ok = False
    finally:
        pc.destroy()
        A.destroy()
    return ok


def versions():
    """Versions of everything a result depends on (also written into every HDF5 file)."""
    import platform

    import numpy
    import mpi4py
    from mpi4py import MPI

    from parjam import __version__

    PETSc = init()
    SLEPc = slepc()
    return {
        "parjam": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "petsc": "%d.%d.%d" % PETSc.Sys.getVersion(),
        "slepc": "%d.%d.%d" % SLEPc.Sys.getVersion(),
        "mpi4py": mpi4py.__version__,
        "mpi": MPI.Get_library_version().splitlines()[0].strip(),
        "petsc_dir": os.environ.get("PETSC_DIR", ""),
    }
