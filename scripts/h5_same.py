#!/usr/bin/env python3
"""Compare two HDF5 files object by object: the same groups and datasets, each dataset's dtype,
shape and values, and every attribute.  Run-dependent attributes (timings, the command line,
the rank count, PETSc options, solver statistics) are listed apart, not compared; ``--rtol``
compares float values to a tolerance (0: bit for bit).  Exit status 1 when they differ.

    .venv/bin/python scripts/h5_same.py A.h5 B.h5 [--rtol 1e-8] [--abs-vectors]

``--abs-vectors``: eigenvectors compared up to the sign of each mode (and, as in any
eigensolver, only where the eigenvalues are simple).
"""

import argparse
import sys

import h5py
import numpy as np

RUN_DEPENDENT = {"seconds", "command_line", "ranks", "petsc_options", "solver_info", "versions",
                 "peak_rss_mb", "seconds_count", "seconds_null_space", "seconds_analysis"}


def walk(f):
    out = {}
    f.visititems(lambda name, obj: out.__setitem__(name, obj))
    out["/"] = f
    return out


def same_value(a, b, rtol):
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype.kind != b.dtype.kind:
        return False
    if a.dtype.kind == "f" and rtol > 0:
        return bool(np.allclose(a, b, rtol=rtol, atol=rtol * max(np.abs(a).max(initial=0), 1e-300),
                                equal_nan=True))
    if a.dtype.kind == "f":
        return bool(np.array_equal(a, b, equal_nan=True))
    if a.dtype.kind == "O":  # object references: compared by existence only
        return True
    return bool(np.array_equal(a, b))


def differences(pa, pb, rtol=0.0, abs_vectors=False):
    """(differences, skipped run-dependent attributes) of two files."""
    diffs, skipped = [], []
    with h5py.File(pa, "r") as fa, h5py.File(pb, "r") as fb:
        ia, ib = walk(fa), walk(fb)
        for name in sorted(set(ia) ^ set(ib)):
            diffs.append(f"{name}: only in {'A' if name in ia else 'B'}")
        for name in sorted(set(ia) & set(ib)):
            oa, ob = ia[name], ib[name]
            if isinstance(oa, h5py.Dataset) != isinstance(ob, h5py.Dataset):
                diffs.append(f"{name}: dataset vs group")
                continue
            if isinstance(oa, h5py.Dataset):
                va, vb = oa[()], ob[()]
                if oa.dtype != ob.dtype:
                    diffs.append(f"{name}: dtype {oa.dtype} vs {ob.dtype}")
                elif abs_vectors and name.endswith("eigenvector"):
                    if not same_value(np.abs(va), np.abs(vb), max(rtol, 1e-6)):
                        diffs.append(f"{name}: |values| differ")
                elif not same_value(va, vb, rtol):
                    diffs.append(f"{name}: values differ")
            for key in sorted(set(oa.attrs) | set(ob.attrs)):
                if key in RUN_DEPENDENT:
                    skipped.append(f"{name}@{key}")
                    continue
                if key not in oa.attrs or key not in ob.attrs:
                    diffs.append(f"{name}@{key}: only in {'A' if key in oa.attrs else 'B'}")
                elif not same_value(oa.attrs[key], ob.attrs[key], rtol):
                    diffs.append(f"{name}@{key}: {oa.attrs[key]!r} vs {ob.attrs[key]!r}")
    return diffs, skipped


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--rtol", type=float, default=0.0)
    ap.add_argument("--abs-vectors", action="store_true")
    args = ap.parse_args()
    diffs, skipped = differences(args.a, args.b, args.rtol, args.abs_vectors)
    print(f"not compared (run-dependent): {', '.join(sorted(set(skipped)))}")
    print("\n".join(diffs) if diffs else "same datasets, dtypes, shapes, values and attributes")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
