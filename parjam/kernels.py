"""The compiled pair-force kernel (``_kernels.c``), built on first use with the system's C
compiler and loaded through ctypes; a numpy implementation with the same results (to round-off)
serves when no compiler is available or ``PARJAM_KERNELS=numpy`` is set.

The shared library is built once per source version into ``$PARJAM_CACHE`` (default
``~/.cache/parjam``), under a temporary name renamed into place, so concurrent MPI ranks can race
for it safely.
"""

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from parjam import potential
from parjam.system import pair_separation

_SRC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_kernels.c")
_lib = None
_tried = False


def _cache_dir():
    return os.environ.get("PARJAM_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "parjam"))


def _build():
    src = open(_SRC, "rb").read()
    tag = hashlib.sha256(src).hexdigest()[:16]
    target = os.path.join(_cache_dir(), f"_kernels-{tag}.so")
    if os.path.exists(target):
        return target
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    os.makedirs(_cache_dir(), exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=_cache_dir())
    os.close(fd)
    # no -ffast-math: the summation order and IEEE semantics are part of the results
    cmd = [cc, "-O2", "-fPIC", "-shared", "-o", tmp, _SRC, "-lm"]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        os.remove(tmp)
        print(f"parjam: warning: could not compile the force kernel ({res.stderr.strip()[:200]});"
              " using numpy", file=sys.stderr)
        return None
    os.replace(tmp, target)
    return target


def library():
    """The loaded kernel library, or None (numpy fallback)."""
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("PARJAM_KERNELS", "").lower() == "numpy":
        return None
    try:
        path = _build()
    except OSError:
        path = None
    if path is None:
        return None
    lib = ctypes.CDLL(path)
    f = lib.parjam_pair_forces
    f.restype = ctypes.c_double
    ptr = np.ctypeslib.ndpointer
    f.argtypes = [ctypes.c_int64, ptr(np.int64, flags="C"), ptr(np.int64, flags="C"),
                  ptr(np.float64, flags="C"), ptr(np.float64, flags="C"), ctypes.c_double,
                  ctypes.c_int, ctypes.c_double, ctypes.c_double, ctypes.c_int64, ctypes.c_int64,
                  ptr(np.float64, flags="C,W")]
    _lib = lib
    return _lib


def pair_forces(pi, pj, pos, diam, L, alpha, eps, lo, hi, out):
    """Forces on the owned particles [lo, hi) into ``out`` ((hi-lo, d), C order); returns the
    energy of the pairs whose first particle is owned."""
    lib = library()
    if lib is not None:
        return lib.parjam_pair_forces(len(pi), pi, pj, pos, diam, L, pos.shape[1], alpha, eps,
                                      lo, hi, out)
    return pair_forces_numpy(pi, pj, pos, diam, L, alpha, eps, lo, hi, out)


def pair_forces_numpy(pi, pj, pos, diam, L, alpha, eps, lo, hi, out):
    """The numpy version of the compiled pair-force kernel (same arguments, same result): used
    when the C kernel is not built, and as its reference in the tests."""
    rij = pair_separation(pos[pi], pos[pj], L)
    r = np.sqrt(np.einsum("ij,ij->i", rij, rij))
    sigma = 0.5 * (diam[pi] + diam[pj])
    c = r < sigma
    i, j, rij, r, sigma = pi[c], pj[c], rij[c], r[c], sigma[c]
    fj = -(potential.dV(r, sigma, alpha, eps) / r)[:, None] * rij
    own_i = (i >= lo) & (i < hi)
    own_j = (j >= lo) & (j < hi)
    idx = np.concatenate([i[own_i], j[own_j]]) - lo
    for a in range(pos.shape[1]):
        w = np.concatenate([-fj[own_i, a], fj[own_j, a]])
        out[:, a] = np.bincount(idx, weights=w, minlength=hi - lo)
    return potential.energy(r[own_i], sigma[own_i], alpha, eps).sum()
