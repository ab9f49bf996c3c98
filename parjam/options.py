"""PETSc options the user gave on the command line: the ones no solver read are reported at the
end of a command, each as a one-line warning naming the nearest valid option; a value PETSc
rejects becomes a one-line error.

PETSc itself marks an option "used" when an object's setFromOptions (or any query) reads it;
``-options_left`` prints the rest at PetscFinalize.  petsc4py (3.18) does not expose that list,
so :func:`unused` asks the PETSc library it loaded for it (PetscOptionsLeftGet, through ctypes).
The valid options are the prefixes parjam gives its solvers (``modes_``, ``newton_``, ...)
combined with the options of those PETSc/SLEPc objects, plus PETSc's global options.
"""

import ctypes
import difflib
import functools
import os

import numpy as np

from parjam import env

# options prefixes of parjam's solvers, the commands that create them first
PREFIXES = {"modes": ("modes_",), "pack": ("newton_",), "moduli": ("moduli_",),
            "softmodes": ("soft_", "soft_inertia_", "soft_gap_"),
            "lengths": ("lengths_inertia_", "modes_"), "run": ("newton_", "modes_")}
ALL_PREFIXES = ("modes_", "newton_", "moduli_", "soft_", "soft_inertia_", "soft_gap_",
                "lengths_inertia_")

_KSP = ("ksp_type", "ksp_rtol", "ksp_atol", "ksp_max_it", "ksp_monitor", "ksp_view",
        "ksp_converged_reason", "ksp_norm_type", "ksp_error_if_not_converged", "pc_type",
        "pc_factor_mat_solver_type", "pc_factor_mat_ordering_type", "pc_gamg_threshold",
        "pc_gamg_agg_nsmooths", "pc_view", "mat_mumps_icntl_4", "mat_mumps_icntl_7",
        "mat_mumps_icntl_13", "mat_mumps_icntl_14", "mat_mumps_icntl_24", "mat_mumps_icntl_28",
        "mat_mumps_icntl_29", "mat_mumps_cntl_1", "mat_mumps_cntl_3")
_EPS = ("eps_type", "eps_nev", "eps_ncv", "eps_mpd", "eps_tol", "eps_max_it", "eps_target",
        "eps_view", "eps_view_values", "eps_monitor", "eps_monitor_all", "eps_converged_reason",
        "eps_conv_abs", "eps_conv_rel", "eps_interval", "eps_krylovschur_partitions",
        "eps_krylovschur_detect_zeros", "eps_true_residual", "eps_purify", "eps_error_absolute",
        "eps_error_relative", "eps_smallest_real", "eps_target_magnitude", "st_type",
        "st_shift", "st_view") + tuple("st_" + k for k in _KSP)
GLOBAL = ("log_view", "log_summary", "log_trace", "options_left", "options_view", "help",
          "info", "malloc_debug", "malloc_dump", "memory_view", "on_error_abort", "fp_trap",
          "start_in_debugger", "check_pointer_intensity", "use_gpu_aware_mpi")


@functools.lru_cache(maxsize=None)
def valid_names():
    """Every option name (without the dash) that some solver of parjam, or PETSc, reads."""
    names = set(GLOBAL)
    for prefix in ALL_PREFIXES:
        names.update(prefix + k for k in _KSP + _EPS)
    return frozenset(names)


def suggestion(name, command=None):
    """The nearest valid option to ``name`` (no dash), or None: the same option under a prefix
    of the command's solvers first (-eps_view -> -modes_eps_view), else the closest spelling."""
    valid = valid_names()
    order = PREFIXES.get(command, ()) + ALL_PREFIXES
    for prefix in order:
        if not name.startswith(prefix) and prefix + name in valid:
            return prefix + name
    close = difflib.get_close_matches(name, sorted(valid), n=1, cutoff=0.8)
    return close[0] if close else None


def user_option_names(petsc_args):
    """The option names (no dash) among the PETSc arguments of the command line."""
    return [a[1:] for a in petsc_args if a.startswith("-") and not _is_number(a)]


def _is_number(text):
    try:
        float(text)
        return True
    except ValueError:
        return False


@functools.lru_cache(maxsize=None)
def _library():
    """The PETSc shared library petsc4py loaded (None if it cannot be found)."""
    try:
        with open("/proc/self/maps") as fh:
            paths = {line.split()[-1] for line in fh if "libpetsc" in line and ".so" in line}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
            lib.PetscOptionsLeftGet  # noqa: B018  (attribute lookup: is the symbol there?)
            return lib
        except (OSError, AttributeError):
            continue
    return None


def unused():
    """Names (no dash) of the options in PETSc's database that nothing has read, or None when
    the library's list is unreachable."""
    PETSc = env.petsc()
    lib = _library()
    if lib is None:
        return None

    int_type = {4: ctypes.c_int32, 8: ctypes.c_int64}[np.dtype(PETSc.IntType).itemsize]
    n = int_type(0)
    names = ctypes.POINTER(ctypes.c_char_p)()
    values = ctypes.POINTER(ctypes.c_char_p)()
    if lib.PetscOptionsLeftGet(None, ctypes.byref(n), ctypes.byref(names), ctypes.byref(values)):
        return None
    try:
        return [names[k].decode() for k in range(n.value)]
    finally:
        lib.PetscOptionsLeftRestore(None, ctypes.byref(n), ctypes.byref(names),
                                    ctypes.byref(values))


def warnings_for(petsc_args, command=None):
    """One line per option the user gave that no solver read: '-X was not used; did you mean
    -Y?'.  Options that PETSc reads only at finalisation (-log_view, -options_left, ...) are
    never reported."""
    left = unused()
    if left is None:
        return []
    left = set(left)
    lines = []
    for name in user_option_names(petsc_args):
        if name not in left or name in GLOBAL:
            continue
        if name in valid_names():  # a valid name whose solver did not run this time
            lines.append(f"-{name} was not used: no solver that reads it ran")
            continue
        hint = suggestion(name, command)
        lines.append(f"-{name} was not used" + (f"; did you mean -{hint}?" if hint else
                                                 " (no solver of this command reads it)"))
    return lines


PETSC_INPUT_ERRORS = (56, 60, 62, 63, 86)  # no support, sizes, wrong argument, out of range,
# unknown type: what a bad option value raises in setFromOptions


def option_error(exc, petsc_args):
    """A one-line message for a PETSc error that a bad option value caused, else None."""
    code = getattr(exc, "ierr", None)
    if code not in PETSC_INPUT_ERRORS or not user_option_names(petsc_args):
        return None
    detail = ""
    for line in reversed(list(getattr(exc, "_traceback_", None) or [])):
        text = str(line).split("]", 1)[-1].strip()
        if text and "()" not in text and "petsc.org" not in text:
            detail = text
            break
    given = " ".join(petsc_args)
    return (f"PETSc rejected an option: {detail or f'error code {code}'} (PETSc options given: "
            f"{given})")


# --------------------------------------------------------------------------- the user's options
# PETSc reads its options (command line, PETSC_OPTIONS, -options_file and the rc files) inside
# PetscInitialize: parjam.files.petscfiles looks at the files they name first, from the tokens
# parsed here.


def environment_args():
    """The PETSc options of the PETSC_OPTIONS environment variable, as tokens (they reach the
    options database like the command line's, so they get the same checks and messages)."""
    import shlex

    text = os.environ.get("PETSC_OPTIONS", "")
    try:
        return shlex.split(text)
    except ValueError:  # an unbalanced quote: PETSc splits at white space
        return text.split()


def pairs(tokens):
    """(name without dash, value or None) of option tokens: a value is the next token when it
    is not itself an option (a negative number is a value)."""
    out, k = [], 0
    while k < len(tokens):
        tok = tokens[k]
        if tok.startswith("-") and len(tok) > 1 and not _is_number(tok):
            nxt = tokens[k + 1] if k + 1 < len(tokens) else None
            if nxt is not None and (not nxt.startswith("-") or _is_number(nxt)):
                out.append((tok[1:], nxt))
                k += 2
                continue
            out.append((tok[1:], None))
        k += 1
    return out


#: viewer types whose second field is a file name (socket, draw, saws, glvis: a host or display)
FILE_VIEWERS = ("", "ascii", "binary", "hdf5", "vtk", "matlab", "adios")


def destinations(tokens):
    """(option, file) of every file that options make PETSc write: viewers (``-log_view
    :FILE``, ``-X_view ascii:FILE:format``, monitors), ``-log_trace FILE``, ``-info FILE``,
    ``-history FILE``."""
    out = []
    for name, value in pairs(tokens):
        if not value:
            continue
        path = None
        if name in ("log_trace", "history"):
            path = value
        elif name == "info":
            path = value.split(":", 1)[0] or None
        elif ("view" in name or "monitor" in name) and ":" in value:
            fields = value.split(":")
            if fields[0] in FILE_VIEWERS and fields[1]:
                path = fields[1]
        if path:
            out.append((f"-{name}", path))
    return out


def all_user_args(petsc_args):
    """The command line's PETSc options and PETSC_OPTIONS' (for messages and warnings)."""
    return list(petsc_args or []) + environment_args()
