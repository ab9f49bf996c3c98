"""Compare two parjam HDF5 files by their results: every dataset bitwise and the /parameters
attributes, ignoring provenance (/h5md: versions, command line, ranks) and wall-clock times."""

import h5py
import numpy as np

IGNORED_ATTRS = ("seconds", "group_ranks")


def datasets(path):
    """{name: array} of every dataset outside /h5md."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and not name.startswith("h5md"):
                out[name] = obj[()]
        f.visititems(visit)
    return out


def parameters(path):
    with h5py.File(path, "r") as f:
        attrs = dict(f["parameters"].attrs) if "parameters" in f else {}
    return {k: v for k, v in attrs.items() if k not in IGNORED_ATTRS}


def differences(a, b):
    """Names of the datasets/parameters that differ between files a and b (empty: same)."""
    da, db = datasets(a), datasets(b)
    diff = sorted(set(da) ^ set(db))
    for name in sorted(set(da) & set(db)):
        if not same_values(da[name], db[name], dtypes=True):
            diff.append(name)
    pa, pb = parameters(a), parameters(b)
    for key in sorted(set(pa) | set(pb)):
        if key not in pa or key not in pb or not same_values(pa[key], pb[key]):
            diff.append(f"parameters/{key}")
    return diff


def same_values(x, y, dtypes=False):
    """Bitwise-equal values, NaN equal to NaN (an undefined result stored twice is the same)."""
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape or (dtypes and x.dtype != y.dtype):
        return False
    return np.array_equal(x, y, equal_nan=x.dtype.kind == "f" and y.dtype.kind == "f")


def assert_same_member(fa, fb, name=""):
    """Two open packing files of one member made on different rank counts agree to the
    round-off a shared member allows: phi_c to 1e-12, pressure to 1e-5 relative, the
    non-rattlers' positions to 1e-7 after removing the global translation (a zero mode).  Why
    these bounds: the docstring of the comparison in tests/pack/test_checkpoint.py."""
    from parjam.files.h5md import observable

    phi_a, phi_b = fa["parameters"].attrs["phi_c"], fb["parameters"].attrs["phi_c"]
    assert abs(phi_a - phi_b) <= 1e-12 * phi_b, name
    pa, pb = observable(fa, "pressure"), observable(fb, "pressure")
    assert abs(pa - pb) <= 1e-5 * pb, name
    backbone = ~fb["particles/all/rattler"][()].astype(bool)
    L = fb["particles/all/box/edges/value"][0]
    du = fa["particles/all/position/value"][0] - fb["particles/all/position/value"][0]
    du = (du - L * np.round(du / L))[backbone]
    assert np.abs(du - du.mean(axis=0)).max() <= 1e-7, name
