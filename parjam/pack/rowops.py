"""The engine's compiled row operations on its per-rank arrays (``_kernels.c``, loaded by
parjam.pack.kernels): folding positions into the box with their slabs, merging the rows a rank
keeps with those handed to it, and gathering rows by index.  Each gives numpy's bits and falls
back to numpy where there is no compiled library."""

import ctypes

import numpy as np

from parjam.pack.kernels import library


def fold_owner(x, L, bounds=None, folded=False):
    """Positions ``x`` (n, d) folded into the box [0, L) as parjam.net.domain.SlabDomain.fold
    folds them (the same bits; not if ``folded``: x is, already), and, given the slab
    ``bounds`` (P + 1 values along axis 0), the owning slab of each row as
    SlabDomain.owner(folded=True) gives it; in one compiled pass.  Returns (folded positions,
    owners or None)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    n = len(x)
    d = x.shape[1] if x.ndim > 1 else 1
    out = x if folded else np.empty_like(x)
    nb = 0 if bounds is None else len(bounds) - 1
    owner = None
    if nb:
        bounds = np.ascontiguousarray(bounds, dtype=np.float64)
        owner = np.empty(n, dtype=np.int64)
    lib = library()
    if lib is None:
        if not folded:
            out[...] = np.maximum(x - L * np.floor(x * (1.0 / L)), 0.0)
        if nb:
            owner[...] = np.clip(np.searchsorted(bounds, out[:, 0], side="right") - 1, 0, nb - 1)
        return out, owner
    lib.parjam_fold_owner(n, d, x.ctypes.data, float(L), 1.0 / float(L), nb,
                          bounds.ctypes.data if nb else None,
                          None if folded else out.ctypes.data,
                          owner.ctypes.data if nb else None)
    return out, owner


def search_points(src, pos, offset, L, ref=None):
    """``pos.take(src, axis=0) + offset`` folded into [0, L) along axes 1 .. d - 1 as
    ``fold_owner`` folds (axis 0 left open), and, given ``ref`` (nref, d), ref = pos[:nref]
    copied alongside; in one compiled pass (the same bits as numpy).  The engine's search-only
    rebuild places its plan's points so."""
    pos = np.ascontiguousarray(pos, dtype=np.float64)
    src = np.ascontiguousarray(src, dtype=np.int64)
    offset = np.ascontiguousarray(offset, dtype=np.float64)
    n, d = offset.shape
    if len(src) != n or pos.shape[1:] != (d,) or (n and (src.min() < 0 or src.max() >= len(pos))):
        raise ValueError("search_points: src, pos and offset do not match")
    if ref is not None and (ref.dtype != np.float64 or not ref.flags.c_contiguous
                            or ref.shape[1:] != (d,) or len(ref) > len(pos)):
        raise ValueError("search_points: ref must be C-contiguous float64 rows of pos's width")
    out = np.empty((n, d))
    lib = library()
    if lib is None:
        np.take(pos, src, axis=0, out=out)
        out += offset
        rest = out[:, 1:]
        rest[...] = np.maximum(rest - L * np.floor(rest * (1.0 / L)), 0.0)
        if ref is not None:
            ref[...] = pos[:len(ref)]
        return out
    lib.parjam_search_points(n, d, src.ctypes.data, pos.ctypes.data, offset.ctypes.data,
                             float(L), 1.0 / float(L), out.ctypes.data,
                             0 if ref is None else len(ref),
                             None if ref is None else ref.ctypes.data)
    return out


def merge_rows(rows, old, fresh):
    """``np.concatenate([old, fresh]).take(rows, axis=0)`` in one compiled pass (rows of float64
    or int64, any trailing shape; the same bits)."""
    old, fresh = np.ascontiguousarray(old), np.ascontiguousarray(fresh, dtype=old.dtype)
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    lib = library()
    if (lib is None or old.dtype.itemsize != 8 or old.shape[1:] != fresh.shape[1:]
            or (len(rows) and (rows.min() < 0 or rows.max() >= len(old) + len(fresh)))):
        return np.concatenate([old, fresh]).take(rows, axis=0)
    out = np.empty((len(rows),) + old.shape[1:], dtype=old.dtype)
    w = int(np.prod(old.shape[1:], dtype=np.int64))
    lib.parjam_merge_rows(len(rows), w, rows.ctypes.data, len(old), old.ctypes.data,
                          fresh.ctypes.data, out.ctypes.data)
    return out


class RowGather:
    """``dst[k] = src[idx[k]]`` for rows of (n, d) float64 arrays, bound to its arrays once (as
    FireKernel: a call passes no array through ctypes' checks); np.take where there is no
    library.  The engine packs the ghosts' forces and unpacks them with two of these every
    step."""

    def __init__(self, idx, src, dst):
        self.arrays = (idx, src, dst)
        if (idx.dtype != np.int64 or src.dtype != np.float64 or dst.dtype != np.float64
                or not all(a.flags.c_contiguous for a in self.arrays)
                or len(dst) != len(idx) or src.shape[1:] != dst.shape[1:]):
            raise ValueError("RowGather needs C-contiguous int64 idx and float64 (n, d) rows")
        if len(idx) and (idx.min() < 0 or idx.max() >= len(src)):
            raise ValueError("RowGather: an index outside the source rows")
        lib = library()
        self.fn = None
        if lib is not None:
            fn = lib["parjam_gather_rows"]
            vp = ctypes.c_void_p
            fn.restype = None
            fn.argtypes = [ctypes.c_int64, ctypes.c_int, vp, vp, vp]
            self.fn = fn
            self.args = (len(idx), dst.shape[1] if dst.ndim > 1 else 1,
                         *(a.ctypes.data for a in self.arrays))

    def __call__(self):
        if self.fn is None:
            idx, src, dst = self.arrays
            np.take(src, idx, axis=0, out=dst)
        else:
            self.fn(*self.args)
