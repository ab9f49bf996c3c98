"""Hostile input, property-based (hypothesis): the packing reader and the options of every command.

Properties:
- ``read_packing`` of any mutated file (wrong shapes and dtypes, NaN/inf, non-positive diameters
  or box edges, duplicated particles, absurd N, bad attributes, truncated or non-HDF5 bytes)
  either returns a valid packing or raises ParjamError, never anything else; the mutations that
  make a file invalid are always refused;
- every command given an invalid file or an invalid option value ends with exactly one line
  ``parjam: error: ...`` on stderr, a non-zero status, no traceback, and writes no result.

Runs in-process (``parjam.cli.main``) on both passes: examples are derandomised so that both
ranks of the MPI pass draw the same ones (the errors are collective); each rank works in its own
temporary directory.  A few subprocess checks (serial) confirm the exit status and stderr.
"""

import contextlib
import io
import os
import shutil
import subprocess
import sys
import tempfile

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from parjam import cli
from parjam.errors import ParjamError
from parjam.files.h5md import read_packing
from conftest import ROOT

SOURCE = os.path.join(ROOT, "tests", "data", "soft_d2_N64_m0.h5")  # 2D, N = 64, dphi = 1e-8
N, D = 64, 2
POS = "particles/all/position/value"
DIAM = "particles/all/diameter"
EDGES = "particles/all/box/edges"

# PARJAM_HYPOTHESIS_EXAMPLES raises the count for a thorough run (docs/explanation/reliability.md)
EXAMPLES = int(os.environ.get("PARJAM_HYPOTHESIS_EXAMPLES", "25"))
HOSTILE = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@contextlib.contextmanager
def workdir():
    path = tempfile.mkdtemp(prefix="parjam-hostile-")
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


def copy_source(directory, name="p.h5"):
    path = os.path.join(directory, name)
    shutil.copy(SOURCE, path)
    return path


def run_cli(argv):
    """(status, stdout, stderr) of an in-process ``parjam`` call."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def assert_clean_error(rc, err, outputs=()):
    """Non-zero status, no traceback, one line ``parjam: error: ...`` (on rank 0: a collective
    error is printed once), no output file."""
    from mpi4py import MPI

    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert rc != 0, err
    assert "Traceback" not in err, err
    if MPI.COMM_WORLD.Get_rank() == 0 or lines:
        assert len(lines) == 1 and lines[0].startswith("parjam: error: "), err
    for path in outputs:
        assert not os.path.exists(path), f"{path} was written"


def assert_valid(pack):
    assert pack.pos.ndim == 2 and pack.pos.shape[1] in (2, 3) and pack.n >= 2
    assert np.all(np.isfinite(pack.pos)) and np.all((pack.pos >= 0) & (pack.pos < pack.L))
    assert np.all(np.isfinite(pack.diam)) and np.all(pack.diam > 0)
    assert np.isfinite(pack.L) and pack.L > 2 * pack.diam.max()
    assert pack.alpha > 1 and np.isfinite(pack.eps) and pack.eps > 0


# --- mutations of a valid file ---------------------------------------------------------------
def _replace(f, name, value):
    del f[name]
    f[name] = value


def _nonfinite(data):
    target = data.draw(st.sampled_from([POS, DIAM, EDGES]))
    value = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]))
    def mutate(f):
        arr = f[target][()]
        flat = arr.reshape(-1)
        flat[data.draw(st.integers(0, flat.size - 1))] = value
        _replace(f, target, arr)
    return mutate


def _nonpositive(data):
    target = data.draw(st.sampled_from([DIAM, EDGES]))
    value = data.draw(st.floats(max_value=0.0, allow_nan=False, allow_infinity=True))
    def mutate(f):
        arr = f[target][()]
        if target == EDGES:
            arr[:] = value  # all edges: unequal edges are another error
        else:
            arr[data.draw(st.integers(0, arr.size - 1))] = value
        _replace(f, target, arr)
    return mutate


def _duplicate(data):
    i, j = data.draw(st.lists(st.integers(0, N - 1), min_size=2, max_size=2, unique=True))
    image = np.array(data.draw(st.lists(st.integers(-2, 2), min_size=D, max_size=D)), float)
    def mutate(f):
        pos = f[POS][()]
        L = f[EDGES][0]
        pos[0, j] = pos[0, i] + image * L  # the same particle, possibly a periodic image
        _replace(f, POS, pos)
    return mutate


def _wrong_shape_or_dtype(data):
    target = data.draw(st.sampled_from([POS, DIAM, EDGES]))
    dtype = data.draw(st.sampled_from(["f8", "f4", "i4", "u1", "c16", "S4", "?"]))
    shape = data.draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=70))
    arr = data.draw(hnp.arrays(np.dtype(dtype), shape))
    def mutate(f):
        _replace(f, target, arr)
    return mutate


def _bad_attribute(data):
    key = data.draw(st.sampled_from(["alpha", "epsilon"]))
    value = data.draw(st.one_of(
        st.floats(max_value=1.0) if key == "alpha" else st.floats(max_value=0.0),
        st.sampled_from([np.nan, np.inf, -np.inf]), st.text(max_size=5),
        st.lists(st.floats(2, 3), min_size=2, max_size=3).map(np.array)))
    def mutate(f):
        f["parameters"].attrs[key] = value
    return mutate


def _structural(data):
    what = data.draw(st.sampled_from(["missing", "group", "empty series", "huge", "one"]))
    target = data.draw(st.sampled_from([POS, DIAM, EDGES]))
    def mutate(f):
        if what == "missing":
            del f[target]
        elif what == "group":
            del f[target]
            f.create_group(target)
        elif what == "empty series":
            _replace(f, POS, np.zeros((0, N, D)))
        elif what == "huge":  # absurd N: declared, never allocated, must not be read
            del f[POS]
            f.create_dataset(POS, shape=(1, 10**9, D), dtype="f8")
            del f[DIAM]
            f.create_dataset(DIAM, shape=(10**9,), dtype="f8")
        else:
            _replace(f, POS, f[POS][()][:, :1])
            _replace(f, DIAM, f[DIAM][()][:1])
    return mutate


MUST_FAIL = [_nonfinite, _nonpositive, _duplicate, _bad_attribute, _structural]


def mutated_file(directory, mutate):
    path = copy_source(directory)
    with h5py.File(path, "a") as f:
        mutate(f)
    return path


def damaged_bytes(directory, data):
    """Truncated at any point, garbage, or a garbage tail behind the HDF5 signature."""
    raw = open(SOURCE, "rb").read()
    kind = data.draw(st.sampled_from(["truncated", "garbage", "signature"]))
    if kind == "truncated":
        body = raw[: data.draw(st.integers(0, len(raw) - 1))]
    elif kind == "garbage":
        body = data.draw(st.binary(max_size=2048))
    else:
        body = raw[:8] + data.draw(st.binary(min_size=1, max_size=2048))
    path = os.path.join(directory, "damaged.h5")
    with open(path, "wb") as fh:
        fh.write(body)
    return path


# --- the reader ------------------------------------------------------------------------------
@HOSTILE
@given(data=st.data())
def test_reader_refuses_invalid_files(data):
    with workdir() as tmp:
        make = data.draw(st.sampled_from(MUST_FAIL))
        path = mutated_file(tmp, make(data))
        with pytest.raises(ParjamError):
            read_packing(path)


@HOSTILE
@given(data=st.data())
def test_reader_never_raises_anything_else(data):
    """Arbitrary shapes and dtypes: a valid packing or a ParjamError."""
    with workdir() as tmp:
        path = mutated_file(tmp, _wrong_shape_or_dtype(data))
        try:
            pack = read_packing(path)
        except ParjamError:
            return
        assert_valid(pack)


@HOSTILE
@given(data=st.data())
def test_reader_refuses_damaged_bytes(data):
    with workdir() as tmp:
        path = damaged_bytes(tmp, data)
        with pytest.raises(ParjamError):
            read_packing(path)


# --- every command on invalid files ----------------------------------------------------------
def file_commands(path, out):
    return {
        "analyze": ["analyze", path],
        "export": ["export", path, "--out", out + ".xyz"],
        "modes": ["modes", path, "--k", "3", "--out", out + ".h5", "-q"],
        "moduli": ["moduli", path, "--out", out + ".h5", "-q"],
        "softmodes": ["softmodes", path, "--cut", "x=0.5", "--out", out + ".h5", "-q"],
        "dos": ["dos", path, "--out", out + ".h5"],
    }


@HOSTILE
@given(data=st.data())
def test_every_command_refuses_invalid_files(data):
    with workdir() as tmp:
        if data.draw(st.booleans()):
            path = mutated_file(tmp, data.draw(st.sampled_from(MUST_FAIL))(data))
        else:
            path = damaged_bytes(tmp, data)
        out = os.path.join(tmp, "result")
        name = data.draw(st.sampled_from(sorted(file_commands(path, out))))
        rc, _, err = run_cli(file_commands(path, out)[name])
        assert_clean_error(rc, err, [out + ".h5", out + ".xyz"])


# --- every command's options -----------------------------------------------------------------
def _num(x):
    return repr(float(x)) if isinstance(x, float) else str(x)


def garbage_text():
    return st.text(min_size=1, max_size=8).filter(lambda s: not _parses(s) and "\x00" not in s)


def _parses(s):
    try:
        float(s)
        return True
    except ValueError:
        return False


NAN_INF = st.sampled_from([float("nan"), float("inf"), float("-inf")])

PACK_BAD = {
    "--dim": st.integers().filter(lambda v: v not in (2, 3)),
    "--n": st.one_of(st.integers(max_value=15), st.integers(min_value=50_000_001)),
    "--alpha": st.one_of(st.floats(max_value=1.0), NAN_INF),
    "--ratio": st.one_of(st.floats(max_value=0.999), st.floats(min_value=10.001), NAN_INF),
    "--members": st.one_of(st.integers(max_value=0), st.integers(min_value=1_000_001)),
    "--seed": st.integers(max_value=-1),
    "--ftol": st.one_of(st.floats(max_value=0.0), st.floats(min_value=1e-3), NAN_INF),
    "--phi": st.one_of(st.floats(max_value=0.049), st.floats(min_value=1.0), NAN_INF),
    "--phi-start": st.one_of(st.floats(max_value=0.049), st.floats(min_value=1.0), NAN_INF),
    "--dphi": st.one_of(st.floats(max_value=0.0), st.floats(min_value=1.0001), NAN_INF),
    "--pressure": st.one_of(st.floats(max_value=0.0), st.floats(min_value=10.0), NAN_INF),
    "--dispersity": st.text(max_size=6).filter(lambda s: s not in ("mono", "bi", "poly")),
}


@HOSTILE
@given(data=st.data())
def test_pack_refuses_invalid_options(data):
    option = data.draw(st.sampled_from(sorted(PACK_BAD)))
    value = data.draw(st.one_of(PACK_BAD[option], garbage_text()) if option != "--dispersity"
                      else PACK_BAD[option])
    with workdir() as tmp:
        out = os.path.join(tmp, "out")
        extra = ["--energy-window", "2e-16", "1e-16"] if data.draw(st.booleans()) else []
        rc, _, err = run_cli(["pack", "--dim", "3", "--n", "16", "--out", out, "-q",
                              f"{option}={_num(value)}"] + extra)
        assert_clean_error(rc, err)
        assert not os.path.exists(out) or not os.listdir(out)


def bad_pair():
    """Frequency windows/plateaus that are not an increasing pair of finite numbers."""
    finite = st.floats(-10, 10, allow_nan=False)
    return st.one_of(
        st.tuples(finite, finite).filter(lambda ab: ab[1] <= ab[0]).map(
            lambda ab: f"{ab[0]!r},{ab[1]!r}"),
        st.tuples(finite, NAN_INF).map(lambda ab: f"{ab[0]!r},{ab[1]!r}"),
        garbage_text(), st.lists(finite, min_size=3, max_size=4).map(
            lambda v: ",".join(map(repr, v))))


MODES_BAD = {
    "--k": st.one_of(st.integers(max_value=0), st.integers(min_value=117)),
    "--tol": st.one_of(st.floats(max_value=0.0), st.floats(min_value=1e-2), NAN_INF),
    "--bins": st.one_of(st.integers(max_value=0), st.integers(min_value=1_000_001)),
    "--target": NAN_INF,
    "--window": bad_pair(),
    "--plateau": bad_pair(),
}


@HOSTILE
@given(data=st.data())
def test_modes_refuses_invalid_options(data):
    option = data.draw(st.sampled_from(sorted(MODES_BAD)))
    value = data.draw(MODES_BAD[option])
    with workdir() as tmp:
        path = copy_source(tmp)
        out = os.path.join(tmp, "spec.h5")
        args = ["modes", path, "--out", out, "-q", f"{option}={_num(value)}"]
        if option != "--window" and option != "--k":
            args += ["--k", "3"]
        elif option == "--window":
            args += ["--method", data.draw(st.sampled_from(["dense", "slice"]))]
        rc, _, err = run_cli(args)
        assert_clean_error(rc, err, [out])


SOFT_BAD = {
    "--cut": st.one_of(garbage_text(), st.floats(1.0, 1e9).map(lambda x: f"x={x!r}"),
                       st.floats(max_value=-1e-9).map(lambda x: f"y={x!r}"),
                       st.just("z=0.5"), NAN_INF.map(lambda x: f"x={x!r}")),
    "--subdivide": st.one_of(st.integers(max_value=0), st.integers(min_value=1001)),
    "--e0": st.one_of(st.floats(max_value=0.0), st.floats(min_value=1.0), NAN_INF),
    "--bins": st.one_of(st.integers(max_value=1), st.integers(min_value=100_001)),
}


@HOSTILE
@given(data=st.data())
def test_softmodes_refuses_invalid_options(data):
    option = data.draw(st.sampled_from(sorted(SOFT_BAD)))
    value = data.draw(SOFT_BAD[option])
    with workdir() as tmp:
        path = copy_source(tmp)
        out = os.path.join(tmp, "soft.h5")
        args = ["softmodes", path, "--out", out, "-q", f"{option}={_num(value)}"]
        if option != "--cut":
            args += ["--cut", "x=0.5"]
        rc, _, err = run_cli(args)
        assert_clean_error(rc, err, [out])


@pytest.mark.parametrize("command", ["modes", "moduli", "softmodes"])
def test_output_over_the_input_is_refused(command):
    """--out naming the input packing (it would be overwritten) or a directory."""
    with workdir() as tmp:
        path = copy_source(tmp)
        before = open(path, "rb").read()
        extra = {"modes": ["--k", "3"], "moduli": [], "softmodes": ["--cut", "x=0.5"]}[command]
        for out in (path, tmp):
            rc, _, err = run_cli([command, path, "--out", out, "-q"] + extra)
            assert_clean_error(rc, err)
        assert open(path, "rb").read() == before


def test_dos_refuses_invalid_spectra_and_options():
    with workdir() as tmp:
        packing = copy_source(tmp)
        spec = os.path.join(tmp, "spec.h5")
        assert run_cli(["modes", packing, "--k", "5", "--out", spec, "-q"])[0] == 0
        out = os.path.join(tmp, "dos.h5")
        for args in ([packing], [spec, "--bins", "0"], [spec, "--bins", "10000000000"],
                     [spec, "--plateau", "2,1"], [spec, "--log-bins", "--omega-min=-1"],
                     [spec, "--out", tmp]):
            rc, _, err = run_cli(["dos"] + args + ([] if "--out" in args else ["--out", out]))
            assert_clean_error(rc, err, [out])


# --- subprocess: the real exit status and stderr ---------------------------------------------
@pytest.mark.serial
@pytest.mark.parametrize("args", [
    ["pack", "--n", "abc"],
    ["pack", "--seed", "-4", "--n", "16"],
    ["modes", "{bad}", "--k", "3", "--out", "{tmp}/s.h5"],
    ["analyze", "{bad}"],
    ["export", "{truncated}"],
    ["moduli", "{dup}"],
    ["softmodes", "{good}", "--cut", "x=0.5", "--out", "{good}"],
    ["frobnicate"],
])
def test_subprocess_one_line_error(tmp_path, args):
    good = copy_source(str(tmp_path), "good.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    raw = open(SOURCE, "rb").read()
    (tmp_path / "truncated.h5").write_bytes(raw[: len(raw) // 3])
    dup = copy_source(str(tmp_path), "dup.h5")
    with h5py.File(dup, "a") as f:
        pos = f[POS][()]
        pos[0, 5] = pos[0, 9]
        _replace(f, POS, pos)
    names = {"bad": str(bad), "truncated": str(tmp_path / "truncated.h5"), "dup": dup,
             "good": good, "tmp": str(tmp_path)}
    argv = [a.format(**names) for a in args]
    before = sorted(os.listdir(tmp_path))
    r = subprocess.run([sys.executable, "-m", "parjam"] + argv, cwd=tmp_path,
                       env=dict(os.environ, PYTHONPATH=ROOT), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("parjam: error: "), r.stderr
    assert sorted(os.listdir(tmp_path)) == before
