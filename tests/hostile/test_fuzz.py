"""Fuzzing (hypothesis) of what a user types: scene files, PETSc options and options files, and
the numeric flags of the command line.

Properties:
- a scene (generated TOML: every value type, nesting, names of any text) is either a Scene
  whose names are one path component and whose integers fit 64 bits, and whose plan and
  dry-run text are made without error, or a ParjamError of one line; never another exception;
- the PETSc option checks (``split_petsc_args``, ``options.pairs``, options files of random
  lines, viewer destinations) never raise anything but ParjamError, and give one line;
- a command given random values of its numeric flags ends with status 0 or with one line
  ``parjam: error: ...``, never a traceback or a warning of numpy.

Every failing example hypothesis found is kept below as an explicit regression example.
Counts: tests/hostile/fuzzing.py (short profile in CI; scripts/fuzz.py for the long one).
"""

import math
import os
import warnings

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from parjam import cli, options
from parjam.errors import ParjamError
from parjam.files import inputs, petscfiles
from parjam.study import plan, scene
from conftest import DATA

from fuzzing import profile, toml_document
from test_hostile_outputs import run_cli

# --------------------------------------------------------------------------- generated scenes

BASE = {
    "system": [{"d": 2, "N": 16, "dispersity": "bi"}],
    "protocol": {"dphi": [1e-3, 1e-2]},
    "ensemble": {"members": 2, "seed": 3},
    "observables": {"contacts": True, "dos": {"bins": 20}},
}

SCALARS = st.one_of(
    st.integers(min_value=-2**70, max_value=2**70), st.integers(min_value=-3, max_value=70),
    st.floats(allow_nan=True, allow_infinity=True), st.booleans(),
    st.text(max_size=12), st.sampled_from(["phi_c", "full", "relaxed", "bi", "mono", "kpm",
                                           "auto", "x=0.5", "extrapolate", ""]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=12)
KEYS = st.sampled_from(["d", "N", "dispersity", "ratio", "alpha", "name", "dphi", "pressure",
                        "ladder", "ftol", "energy_window", "phi_start", "phic_method",
                        "members", "seed", "tol", "dense_max_dof", "small_dof", "contacts",
                        "dos", "lowest", "omega_star", "trans", "softmodes", "moduli",
                        "fluctuations", "pictures", "k", "window", "bins", "matrices", "at",
                        "vectors", "cuts", "subdivide", "e0", "method", "moments", "probes",
                        "description", "unknown"]) | st.text(max_size=6)
TABLES = st.sampled_from([("system", 0), ("protocol",), ("ensemble",), ("observables",),
                          ("observables", "dos"), ("scene",), ("solver",), ()])


def _place(doc, where, key, value):
    """``doc`` with ``value`` at table ``where`` (made if missing), key ``key``."""
    node = doc
    for part in where:
        if isinstance(node, list):
            node = node[part] if part < len(node) else node[-1]
            continue
        if not isinstance(node.get(part), (dict, list)):
            node[part] = {}
        node = node[part]
    if isinstance(node, dict):
        node[key] = value


@st.composite
def scenes(draw):
    import copy

    doc = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(min_value=0, max_value=3))):
        _place(doc, draw(TABLES), draw(KEYS), draw(VALUES))
    if draw(st.booleans()):
        doc["scene"] = {"name": draw(st.text(max_size=20))}
    if draw(st.booleans()):
        doc["system"][0]["name"] = draw(st.text(max_size=20))
    return toml_document(doc)


def _check_scene(text):
    try:
        s = scene.loads(text, "fuzz.toml")
    except ParjamError as exc:
        assert "\n" not in str(exc), str(exc)
        return None
    for name in [s.name] + [x.name for x in s.systems]:
        assert name == inputs.component(name) and os.sep not in name, name
    assert 0 <= s.seed < 2**63 and 1 <= s.members < 2**63
    stages = plan.plan(s)
    assert all(os.sep not in st_.name for st_ in stages)
    plan.describe(s, stages)
    return s


@profile(3)
@given(text=scenes())
@example(text=toml_document({**BASE, "ensemble": {"seed": 99999999999999999999999}}))
@example(text=toml_document({**BASE, "scene": {"name": "../../X"}}))
@example(text=toml_document({**BASE, "system": [{"d": 2, "N": 16, "name": "a\nb"}]}))
@example(text=toml_document({**BASE, "observables": {"contacts": True,
                                                      "dos": {"at": [[[[1e-2]]]]}}}))
@example(text=toml_document({**BASE, "system": [{"d": 2, "N": [16, 16]}]}))
def test_scene_is_a_scene_or_one_line(text):
    _check_scene(text)


@profile(0.5)
@given(depth=st.integers(min_value=1, max_value=6000),
       kind=st.sampled_from(["[", "{a = ", "[{a = "]))
@example(depth=3000, kind="[")
@example(depth=5000, kind="{a = ")
def test_scene_nesting_is_one_line(depth, kind):
    close = {"[": "]", "{a = ": "}", "[{a = ": "}]"}[kind]
    inner = "1" if kind != "[" else ""
    text = toml_document(BASE) + "extra = " + kind * depth + inner + close * depth + "\n"
    with pytest.raises(ParjamError) as err:
        scene.loads(text)
    assert "\n" not in str(err.value)


@profile(1)
@given(text=st.text(max_size=300))
def test_scene_of_any_text(text):
    _check_scene(text)


# --------------------------------------------------------------------------- PETSc options

OPTION_TOKENS = st.lists(st.one_of(
    st.sampled_from(["-options_file", "-options_file_yaml", "-log_view", "-log_trace",
                     "-info", "-history", "-modes_eps_view", "-newton_ksp_monitor",
                     "-skip_petscrc", "-modes_eps_type", "-1e-3", "--", "-"]),
    st.text(max_size=12), st.sampled_from([":x.txt", "ascii:x.txt:ascii_info", "::",
                                          ":/nonexistent/x", "draw:host:0", "binary:",
                                          "opts.txt", "missing.opts", ""])), max_size=8)


@profile(2)
@given(tokens=OPTION_TOKENS, lines=st.lists(st.text(max_size=30), max_size=6))
@example(tokens=["-options_file", "opts.txt"], lines=["-options_file opts.txt"])
@example(tokens=["-log_view", ":/nonexistent/x"], lines=[])
def test_option_checks_are_one_line(tmp_path_factory, tokens, lines):
    work = tmp_path_factory.mktemp("opts")
    with open(work / "opts.txt", "w", encoding="utf-8", errors="replace") as fh:
        fh.write("\n".join(lines))
    cwd = os.getcwd()
    os.chdir(work)
    try:
        ours, petsc = cli.split_petsc_args(tokens)
        assert sorted(ours + petsc) == sorted(tokens)
        options.pairs(tokens)
        for option, path in options.destinations(tokens):
            why = petscfiles.destination_problem(option, path)
            assert why is None or "\n" not in why
        why = petscfiles.startup_problem(tokens)
        assert why is None or "\n" not in why
    finally:
        os.chdir(cwd)


# --------------------------------------------------------------------------- numeric flags

NUMBERS = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "0", "-0", "1e308", "1e-320", "-1", "1e400", "",
                     "0x10", "1_000", "3.5", "2", "16", "64", "1e9", "9" * 30, "-9" * 3,
                     "1,2", "0,1e300", "0,100", "-1,1", "1e-3,1e-2", "nan,1", "x", "1e-2"]),
    st.integers(min_value=-10**20, max_value=10**20).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.tuples(st.floats(allow_nan=True, allow_infinity=True),
              st.floats(allow_nan=True, allow_infinity=True)).map(lambda p: f"{p[0]!r},{p[1]!r}"))

PACK_FLAGS = ["--dim", "--n", "--ratio", "--alpha", "--phi", "--phi-start", "--seed",
              "--members", "--ftol", "--checkpoint-every", "--dphi", "--pressure"]
MODES_FLAGS = ["--k", "--window", "--tol", "--target", "--bins", "--omega-min", "--plateau"]
DOS_FLAGS = ["--bins", "--omega-min", "--plateau"]


def _clean(rc, err):
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("parjam: error:")]
    if rc != 0:
        from mpi4py import MPI

        if MPI.COMM_WORLD.Get_rank() == 0:
            assert len(lines) == 1, err
    else:
        assert not lines, err


def _cli(argv):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy overflow warning is a failure here
        return run_cli(argv)


@pytest.fixture(scope="module")
def spectra(shared_tmp):
    out = []
    for k in range(2):
        path = os.path.join(shared_tmp, f"fuzz-spec{k}.h5")
        rc, _, err = run_cli(["modes", os.path.join(DATA, f"soft_d2_N64_m{k}.h5"), "--k", "20",
                              "--out", path, "-q"])
        assert rc == 0, err
        out.append(path)
    return out


@profile(1)
@given(flag=st.sampled_from(PACK_FLAGS), value=NUMBERS)
@example(flag="--n", value="20000000")
@example(flag="--seed", value="99999999999999999999999")
@example(flag="--dphi", value="nan")
def test_pack_numeric_flags(flag, value):
    argv = ["pack", "--dim", "2", "--dispersity", "bi", "--dry-run", f"{flag}={value}"]
    if flag == "--dim":
        argv.remove("--dim"), argv.remove("2")
    rc, _, err = _cli(argv)
    _clean(rc, err)


@profile(1)
@given(flag=st.sampled_from(MODES_FLAGS), value=NUMBERS)
@example(flag="--window", value="0,1e300")
@example(flag="--window", value="0,100")
@example(flag="--k", value="126")
def test_modes_numeric_flags(shared_tmp, flag, value):
    argv = ["modes", os.path.join(DATA, "soft_d2_N64_m0.h5"), "--out",
            os.path.join(shared_tmp, "fuzz-modes.h5"), "-q", f"{flag}={value}"]
    if flag != "--k" and flag != "--window":
        argv.append("--k=5")
    rc, _, err = _cli(argv)
    _clean(rc, err)
    if rc == 0:
        assert "rejected" not in err, err


@profile(0.5)
@given(flag=st.sampled_from(DOS_FLAGS), value=NUMBERS)
def test_dos_numeric_flags(shared_tmp, spectra, flag, value):
    rc, _, err = _cli(["dos", *spectra, "--out", os.path.join(shared_tmp, "fuzz-dos.h5"), "-q",
                       f"{flag}={value}"])
    _clean(rc, err)


def test_machine_settings_of_any_text(monkeypatch):
    """PARJAM_MEMORY_MB and PARJAM_TIME_LIMIT: a finite positive number, else one line."""
    from parjam import resources

    for text in ("nan", "inf", "-1", "0", "x", "1e400", "NaN", " 5", "1e3"):
        monkeypatch.setenv("PARJAM_MEMORY_MB", text)
        try:
            value = resources.available_memory_mb()
        except ParjamError as exc:
            assert "\n" not in str(exc)
            continue
        assert math.isfinite(value) and value > 0
