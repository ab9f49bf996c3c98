"""The compiled kernels (``_kernels.c``): the pair forces and the fused FIRE step, loaded through
ctypes.  A numpy implementation with the same results (to round-off) serves only as a fall-back,
when no compiled library is available or ``PARJAM_KERNELS=numpy`` is set; it prints a one-line
warning (once, on rank 0) when first used, since it is several times slower.

The library is built at install time (``pip install`` / ``scripts/setup-env``: setup.py's
extension ``parjam.pack._kernels_lib``, next to this file).  It carries the SHA-256 of the source it
was built from; when that is not this ``_kernels.c`` (an edited checkout) or there is none, the
library is built once per source version into ``$PARJAM_CACHE`` (default ``~/.cache/parjam``)
with the system's C compiler, under a temporary name renamed into place, so concurrent MPI
ranks can race for it safely.
"""

import ctypes
import glob
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from parjam.net import exactsum, potential
from parjam.net.system import pair_separation

_HERE = os.path.dirname(os.path.abspath(__file__))
_SRC = os.path.join(_HERE, "_kernels.c")
# no -ffast-math: the summation order and IEEE semantics are part of the results
CFLAGS = ["-O2", "-fPIC", "-fno-fast-math"]
_lib = None
_tried = False
_warned = False
_why = ""

# modes of fire_step (enum in _kernels.c)
FIRE_UPDATE = 1
FIRE_FORCES = 2
FIRE_ENERGY = 4  # with FIRE_FORCES: the energy's exact sum too (else left 0)
# fire_step's sums: energy, F.v, |F|^2, |v|^2, max|F_i|^2, max|v_i|^2, max displacement^2
N_SUMS = 7
# fire_step's buffer of them (FIRE_ACC in _kernels.c): four exact accumulators
# (parjam.net.exactsum) and the bits of the three maxima, reduced over ranks as integers
FIRE_ACC = 4 * exactsum.ACC_LEN + 3


def source_sha():
    """SHA-256 (hex) of ``_kernels.c``: compiled into the library as PARJAM_SRC_SHA."""
    return hashlib.sha256(open(_SRC, "rb").read()).hexdigest()


def _cache_dir():
    return os.environ.get("PARJAM_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "parjam"))


def compile_library(target, cc=None):
    """Compile ``_kernels.c`` into the shared library ``target`` (atomically: a temporary file
    renamed into place).  Returns None on success, else the compiler's message."""
    cc = cc or os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return "no C compiler (cc or gcc) found"
    folder = os.path.dirname(os.path.abspath(target))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=folder)
    os.close(fd)
    cmd = [cc, *CFLAGS, "-shared", f'-DPARJAM_SRC_SHA="{source_sha()}"', "-o", tmp, _SRC, "-lm"]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as exc:
        os.remove(tmp)
        return str(exc)
    if res.returncode != 0:
        os.remove(tmp)
        return res.stderr.strip()[:200] or f"{cc} failed"
    os.replace(tmp, target)
    return None


def _installed():
    """The library built at install time, if it was built from this source."""
    for path in sorted(glob.glob(os.path.join(_HERE, "_kernels_lib*.so"))):
        try:
            lib = ctypes.CDLL(path)
            sha = ctypes.c_char_p.in_dll(lib, "parjam_src_sha").value.decode()
        except (OSError, ValueError):
            continue
        if sha == source_sha():
            return lib
    return None


def _cached():
    """The library built into the cache on first use (None if that fails)."""
    global _why
    target = os.path.join(_cache_dir(), f"_kernels-{source_sha()[:16]}.so")
    if not os.path.exists(target):
        err = compile_library(target)
        if err is not None:
            _why = f"could not compile the kernels ({err})"
            return None
    return ctypes.CDLL(target)


def library():
    """The loaded kernel library, or None (numpy fallback)."""
    global _lib, _tried, _why
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("PARJAM_KERNELS", "").lower() == "numpy":
        _why = "PARJAM_KERNELS=numpy"
        return None
    try:
        lib = _installed() or _cached()
    except OSError as exc:
        _why, lib = f"could not load the kernels ({exc})", None
    if lib is None:
        return None
    ptr = np.ctypeslib.ndpointer
    f64, i64 = ptr(np.float64, flags="C"), ptr(np.int64, flags="C")
    w64 = ptr(np.float64, flags="C,W")
    f = lib.parjam_pair_forces
    f.restype = ctypes.c_double
    wi64 = ptr(np.int64, flags="C,W")
    f.argtypes = [ctypes.c_int64, i64, i64, f64, f64, ctypes.c_double, ctypes.c_int,
                  ctypes.c_double, ctypes.c_double, ctypes.c_int64, ctypes.c_int64, w64,
                  ctypes.c_void_p]
    s = lib.parjam_fire_step
    s.restype = ctypes.c_int
    dbl = ctypes.c_double
    s.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_int, w64, w64, w64, f64,
                  dbl, dbl,
                  ctypes.c_int, dbl, dbl, dbl, dbl, ctypes.c_int64, i64, i64, f64, f64, dbl, dbl,
                  ctypes.c_int64, ctypes.c_int64, wi64]
    xa = lib.parjam_exact_add
    xa.restype = None
    xa.argtypes = [ctypes.c_int64, f64, ctypes.c_int64, wi64]
    xv = lib.parjam_exact_value
    xv.restype = ctypes.c_double
    xv.argtypes = [i64]
    mr = lib.parjam_merge_rows
    mr.restype = None
    mr.argtypes = [ctypes.c_int64, ctypes.c_int, ctypes.c_void_p, ctypes.c_int64,
                   ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    fo = lib.parjam_fold_owner
    fo.restype = None
    fo.argtypes = [ctypes.c_int64, ctypes.c_int, ctypes.c_void_p, dbl, dbl, ctypes.c_int64,
                   ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    sp = lib.parjam_search_points
    sp.restype = None
    sp.argtypes = [ctypes.c_int64, ctypes.c_int] + [ctypes.c_void_p] * 3 + [dbl, dbl,
                                                                           ctypes.c_void_p,
                                                                           ctypes.c_int64,
                                                                           ctypes.c_void_p]
    hp = lib.parjam_halfedge_product
    hp.restype = None
    hp.argtypes = [ctypes.c_int64, ctypes.c_int, ctypes.c_int64, i64, i64, f64, f64, f64, w64]
    fs = lib.parjam_fire_sums
    fs.restype = None
    fs.argtypes = [i64, w64]
    c = lib.parjam_cell_pairs
    c.restype = ctypes.c_int64
    c.argtypes = [ctypes.c_int64, ctypes.c_int, f64, ctypes.c_double, ctypes.c_double,
                  ctypes.c_int, ctypes.c_void_p, dbl, wi64, wi64, wi64, w64, w64, wi64,
                  ctypes.c_int64, wi64, wi64, wi64, wi64]
    sl = lib.parjam_slab_pairs
    sl.restype = ctypes.c_int64
    sl.argtypes = [ctypes.c_int64, ctypes.c_int, f64, dbl, dbl, dbl, dbl, ctypes.c_int64,
                   ctypes.c_int64, ctypes.c_void_p, dbl, i64, i64, i64, ctypes.c_int64, i64,
                   wi64, wi64, wi64, w64, w64, wi64, wi64, wi64, ctypes.c_int64, wi64, wi64,
                   wi64, wi64]
    _lib = lib
    return _lib


def reset():
    """Forget the loaded library (the next call looks again, e.g. after PARJAM_KERNELS changed)."""
    global _lib, _tried, _warned, _why
    _lib, _tried, _warned, _why = None, False, False, ""


def fallback():
    """Warn once (rank 0) that the numpy kernels are in use."""
    global _warned
    if _warned:
        return
    _warned = True
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() == 0:
        print(f"parjam: warning: using the slow numpy force kernels ({_why or 'no library'})",
              file=sys.stderr, flush=True)


def pair_forces(pi, pj, pos, diam, L, alpha, eps, lo, hi, out, acc=None):
    """Forces on the owned particles [lo, hi) into ``out`` ((hi-lo, d), C order); returns the
    energy of the pairs whose first particle is owned, summed in pair order, or, given an
    exact accumulator ``acc`` (parjam.net.exactsum), adds that energy to it exactly (summed
    per lower end first, in pair order) and returns 0."""
    lib = library()
    if lib is not None:
        return lib.parjam_pair_forces(len(pi), pi, pj, pos, diam, L, pos.shape[1], alpha, eps,
                                      lo, hi, out, None if acc is None else acc.ctypes.data)
    fallback()
    return pair_forces_numpy(pi, pj, pos, diam, L, alpha, eps, lo, hi, out, acc)


def pair_forces_numpy(pi, pj, pos, diam, L, alpha, eps, lo, hi, out, acc=None):
    """The numpy version of the compiled pair-force kernel (same arguments, the same bits): used
    when the C kernel is not built, and as its reference in the tests.  The force on a particle
    is summed as the C loop sums it: first as the upper end of its pairs (lower partners
    ascending), then as the lower end (upper partners ascending)."""
    rij = pair_separation(pos[pi], pos[pj], L)
    r2 = rij[:, 0] * rij[:, 0]
    for a in range(1, pos.shape[1]):  # the C loop's order over the components
        r2 = r2 + rij[:, a] * rij[:, a]
    r = np.sqrt(r2)
    sigma = 0.5 * (diam[pi] + diam[pj])
    c = r < sigma
    i, j, rij, r, sigma = pi[c], pj[c], rij[c], r[c], sigma[c]
    fj = -(potential.dV(r, sigma, alpha, eps) / r)[:, None] * rij
    own_i = (i >= lo) & (i < hi)
    own_j = (j >= lo) & (j < hi)
    idx = np.concatenate([j[own_j], i[own_i]]) - lo
    for a in range(pos.shape[1]):
        w = np.concatenate([fj[own_j, a], -fj[own_i, a]])
        out[:, a] = np.bincount(idx, weights=w, minlength=hi - lo)
    e = potential.energy(r[own_i], sigma[own_i], alpha, eps)
    if acc is None:
        return e.sum()
    exactsum.partial(np.bincount(i[own_i] - lo, weights=e, minlength=hi - lo), acc)
    return 0.0


def fire_step(mode, x, v, f, ref, L, dt, reset, back, mix_v, mix_f, stale2, pi, pj, pos, diam,
              alpha, eps, lo, hi, acc, nown=None):
    """One fused FIRE step on the owned particles (x, v, f: (n_all, d) C arrays whose first
    ``nown`` rows (default all) are owned and the rest ghosts, updated alike; ref: (nown, d));
    see ``parjam_fire_step`` in _kernels.c for the modes and the buffer ``acc`` (FIRE_ACC
    int64; ``fire_sums`` reads it).  Returns 1 when the update found the neighbour list stale
    (no forces computed), else 0."""
    nown = len(x) if nown is None else nown
    lib = library()
    if lib is not None:
        return lib.parjam_fire_step(mode, nown, len(x), x.shape[1], x, v, f, ref, L, dt,
                                    int(reset),
                                    back, mix_v, mix_f, stale2, len(pi), pi, pj, pos, diam,
                                    alpha, eps, lo, hi, acc)
    fallback()
    if mode & FIRE_UPDATE:
        if reset:
            x += back * v
            v[:] = 0.0
        v += dt * f
        v[:] = mix_f * f + mix_v * v
        x += dt * v
        disp2 = _max_disp2(x[:nown], ref, L)
        acc[FIRE_ACC - 1:] = np.array([disp2]).view(np.int64)
        if stale2 > 0.0 and disp2 >= stale2:
            return 1
    if mode & FIRE_FORCES:
        n = exactsum.ACC_LEN
        acc[:FIRE_ACC - 1] = 0  # the displacement (last) is the update's, or the caller's
        x, v, f = x[:nown], v[:nown], f[:nown]
        pair_forces_numpy(pi, pj, pos, diam, L, alpha, eps, lo, hi, f,
                          acc[:n] if mode & FIRE_ENERGY else None)
        p, f2, v2 = (np.zeros(len(x)) for _ in range(3))
        for a in range(x.shape[1]):  # the C loop's order over the components
            p += f[:, a] * v[:, a]
            f2 += f[:, a] * f[:, a]
            v2 += v[:, a] * v[:, a]
        for k, part in enumerate((p, f2, v2)):
            exactsum.partial(part, acc[(k + 1) * n:(k + 2) * n])
        acc[FIRE_ACC - 3:FIRE_ACC - 1] = np.array([f2.max(initial=0.0),
                                                   v2.max(initial=0.0)]).view(np.int64)
    return 0


def fire_sums(acc, out=None):
    """The seven numbers of a (reduced) fire_step buffer ``acc``: energy, F.v, |F|^2, |v|^2
    (exact sums rounded to nearest), max |F_i|^2, max |v_i|^2, max displacement^2."""
    out = np.empty(N_SUMS) if out is None else out
    lib = library()
    if lib is not None:
        lib.parjam_fire_sums(acc, out)
        return out
    n = exactsum.ACC_LEN
    out[:4] = [exactsum.value(acc[k * n:(k + 1) * n]) for k in range(4)]
    out[4:] = acc[FIRE_ACC - 3:].view(np.float64)
    return out


class FireKernel:
    """``fire_step`` bound to its arrays (x, v, f: (n_all, d), the first ``nown`` rows owned;
    ref: (nown, d); pi, pj; pos; diam; acc): their addresses are taken once, so a call passes
    scalars only (ctypes' per-array checks cost ~40 us a step, a tenth of a step at
    N = 4096).  The arrays must stay alive and in place while it is used (the engine keeps one
    per neighbour list)."""

    def __init__(self, x, v, f, ref, pi, pj, pos, diam, acc, nown=None):
        self.arrays = (x, v, f, ref, pi, pj, pos, diam, acc)
        kinds = (np.float64,) * 4 + (np.int64,) * 2 + (np.float64,) * 2 + (np.int64,)
        for a, kind in zip(self.arrays, kinds):
            if a.dtype != kind or not a.flags.c_contiguous:
                raise ValueError("FireKernel needs C-contiguous float64/int64 arrays")
        if len(acc) != FIRE_ACC:
            raise ValueError(f"FireKernel's sums buffer holds FIRE_ACC = {FIRE_ACC} int64")
        for a in (x, v, f, acc):
            if not a.flags.writeable:
                raise ValueError("FireKernel writes x, v, f and acc")
        self.nall, self.d, self.npairs = len(x), x.shape[1], len(pi)
        self.nown = self.nall if nown is None else int(nown)
        lib = library()
        self.fn = None
        if lib is not None:
            fn = lib["parjam_fire_step"]  # a new function object: its own argtypes
            vp, dbl, i64 = ctypes.c_void_p, ctypes.c_double, ctypes.c_int64
            fn.restype = ctypes.c_int
            fn.argtypes = [ctypes.c_int, i64, i64, ctypes.c_int, vp, vp, vp, vp, dbl, dbl,
                           ctypes.c_int, dbl, dbl, dbl, dbl, i64, vp, vp, vp, vp, dbl, dbl, i64,
                           i64, vp]
            self.fn = fn
            self.ptr = [a.ctypes.data for a in self.arrays]
            fs = lib["parjam_fire_sums"]
            fs.restype = None
            fs.argtypes = [vp, vp]
            self.fs = fs

    def __call__(self, mode, L, dt, reset, back, mix_v, mix_f, stale2, alpha, eps, lo, hi):
        if self.fn is None:
            x, v, f, ref, pi, pj, pos, diam, acc = self.arrays
            return fire_step(mode, x, v, f, ref, L, dt, reset, back, mix_v, mix_f, stale2, pi,
                             pj, pos, diam, alpha, eps, lo, hi, acc, self.nown)
        x, v, f, ref, pi, pj, pos, diam, acc = self.ptr
        return self.fn(mode, self.nown, self.nall, self.d, x, v, f, ref, L, dt,
                       1 if reset else 0, back,
                       mix_v, mix_f, stale2, self.npairs, pi, pj, pos, diam, alpha, eps, lo, hi,
                       acc)

    def sums(self, out):
        """``fire_sums`` of the bound buffer into ``out`` (N_SUMS float64, C), without
        ctypes' per-call array checks."""
        if self.fn is None:
            return fire_sums(self.arrays[8], out)
        self.fs(self.ptr[8], out.ctypes.data)
        return out


def _max_disp2(x, ref, L):
    dx = x - ref
    dx -= L * np.rint(dx / L)
    return np.einsum("ij,ij->i", dx, dx).max(initial=0.0)
