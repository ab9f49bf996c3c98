"""Fuzzing (hypothesis) of the importers' input formats (parjam.files.importer): generated extended
XYZ headers and columns, LAMMPS data and dump sections, H5MD layouts.

Property, the only one asserted here: ``importer.load`` returns a valid packing (N >= 2 rows of
d = 2 or 3 finite coordinates inside a cubic box of finite positive edge, N positive finite
diameters, the smallest 1) or raises ParjamError with a one-line message; and ``parjam import``
of the same file ends with status 0 and a packing file that ``read_packing`` accepts, or with
one ``parjam: error:`` line and a non-zero status.  Never another exception, a traceback or a
hang.  (Whether an accepted file was read as its writer meant is the importer's own tests'
business.)

Every failing example found is kept below as an explicit example (with the report of the
session that found it).  Counts: tests/hostile/fuzzing.py.
"""

import os


import h5py
import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st

from parjam.errors import ParjamError
from parjam.files import importer
from parjam.files.h5md import read_packing

from fuzzing import profile
from test_hostile_outputs import run_cli

NUM = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                st.floats(min_value=-10, max_value=10), st.integers(-5, 50),
                st.sampled_from([0.0, 1.0, 0.5, 6.0, -1.0, 1e308, 5e-324]))
TOKEN = st.one_of(NUM.map(repr), st.sampled_from(["A", "B", "1", "2", "T", "F", "nan", "inf",
                                                  "", "x", "#", "1e", "--"]),
                  st.text(alphabet="0123456789.-eE+ABTFxyz", max_size=6))


# Importer failures this fuzzing found, each a traceback where one line was due, now fixed in
# parjam.files.importer and kept below as examples: LAMMPS data whose header says N <= 0 atoms
# (StopIteration), and H5MD whose species, diameter or radius is a scalar (TypeError).


def assert_valid(pack):
    n, d = pack.pos.shape
    assert d in (2, 3) and n >= 2 and n == pack.n == len(pack.diam)
    assert np.all(np.isfinite(pack.pos)) and np.all(np.isfinite(pack.diam))
    assert np.isfinite(pack.L) and pack.L > 0
    assert np.all(pack.diam > 0) and np.isclose(pack.diam.min(), 1.0)
    assert np.all(pack.pos >= 0) and np.all(pack.pos <= pack.L)


def load_or_one_line(path, fmt, **kw):
    try:
        pack = importer.load(path, fmt, **kw)
    except ParjamError as exc:
        assert "\n" not in str(exc), str(exc)
        return None
    assert_valid(pack)
    return pack


# --------------------------------------------------------------------------- text mutations

@st.composite
def mutated(draw, base):
    """A valid file's text with 0 to 3 mutations: a line replaced, deleted, duplicated or
    inserted, a token replaced, the line count changed (about one example in five is the
    valid file or a harmless change of it)."""
    lines = base.splitlines()
    for _ in range(draw(st.integers(0, 3))):
        k = draw(st.integers(0, max(len(lines) - 1, 0)))
        how = draw(st.sampled_from(["token", "token", "token", "line", "delete", "duplicate",
                                    "insert", "count"]))
        if not lines:
            lines = [draw(st.text(max_size=20))]
            continue
        words = lines[k].split(" ")
        if how == "token":
            words[draw(st.integers(0, len(words) - 1))] = draw(TOKEN)
            lines[k] = " ".join(words)
        elif how == "line":
            lines[k] = draw(st.text(max_size=40))
        elif how == "delete":
            del lines[k]
        elif how == "duplicate":
            lines.insert(k, lines[k])
        elif how == "insert":
            lines.insert(k, " ".join(draw(st.lists(TOKEN, max_size=8))))
        else:  # the number that says how many rows follow
            lines = [str(draw(st.integers(-3, 12))) if ln.strip().isdigit() else ln
                     for ln in lines]
    return "\n".join(lines) + "\n"


def _rows(n, d, seed, fmt):
    rng = np.random.default_rng(seed)
    grid = [(i, j, k) for i in range(3) for j in range(3) for k in range(3 if d == 3 else 1)]
    pos = (np.array(grid[:n], float) + 0.25 * rng.random((n, 3))) * 1.6
    return [fmt.format(k=k, x=pos[k]) for k in range(n)]


# --------------------------------------------------------------------------- extended XYZ

def _xyz(n, d, props, pbc, extra, fmt):
    box = 4.8
    head = (f'Lattice="{box} 0 0 0 {box} 0 0 0 {box}" Properties={props} pbc="{pbc}"{extra}')
    return f"{n}\n{head}\n" + "\n".join(_rows(n, d, n, fmt)) + "\n"


XYZ_BASES = [
    _xyz(6, 3, "species:S:1:pos:R:3:radius:R:1", "T T T", "",
         "A {x[0]} {x[1]} {x[2]} 0.5"),
    _xyz(6, 2, "species:S:1:pos:R:3:radius:R:1", "T T F", "",
         "A {x[0]} {x[1]} 0.0 0.5"),
    _xyz(8, 3, "type:I:1:pos:R:3:radius:R:1:rattler:I:1", "T T T", " alpha=2.5 dimension=3",
         "{k} {x[0]} {x[1]} {x[2]} 0.4 0"),
    _xyz(5, 3, "species:S:1:pos:R:3", "T T T", "", "B {x[0]} {x[1]} {x[2]}"),
]
VALID_XYZ = XYZ_BASES[0]


@profile(2)
@given(text=st.sampled_from(XYZ_BASES).flatmap(mutated))
@example(text=VALID_XYZ)
@example(text=VALID_XYZ.replace('pbc="T T T"', 'pbc="T T T" dimension=7'))
@example(text=VALID_XYZ.replace("radius:R:1", "radius:R:-1"))
@example(text=VALID_XYZ.replace("4.8 0 0 0 4.8 0 0 0 4.8", "0 0 0 0 0 0 0 0 0"))
def test_extxyz(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("xyz") / "f.xyz"
    path.write_text(text)
    load_or_one_line(str(path), "extxyz")


# --------------------------------------------------------------------------- LAMMPS data

def _data(n, d, style, fmt):
    box = "0 4.8 xlo xhi\n0 4.8 ylo yhi\n0 4.8 zlo zhi" if d == 3 else \
        "0 4.8 xlo xhi\n0 4.8 ylo yhi\n-0.5 0.5 zlo zhi"
    return (f"LAMMPS data file\n\n{n} atoms\n2 atom types\n\n{box}\n\nMasses\n\n1 1.0\n"
            f"2 1.0\n\nAtoms{style}\n\n" + "\n".join(_rows(n, d, n + 1, fmt)) + "\n")


DATA_BASES = [
    _data(6, 3, " # sphere", "{k1} 1 1.0 1.0 {x[0]} {x[1]} {x[2]}".replace("{k1}", "{k}")),
    _data(6, 3, " # atomic", "{k} 1 {x[0]} {x[1]} {x[2]}"),
    _data(5, 2, "", "{k} 1 1.0 1.0 {x[0]} {x[1]} 0.0"),
    _data(6, 3, " # sphere", "{k} 2 1.0 1.0 {x[0]} {x[1]} {x[2]} 0 0 0"),
]
VALID_DATA = DATA_BASES[0]


@profile(2)
@given(text=st.sampled_from(DATA_BASES).flatmap(mutated))
@example(text=VALID_DATA)
@example(text=VALID_DATA.replace("\n6 atoms\n", "\n0 atoms\n", 1))
@example(text=VALID_DATA.replace("\n6 atoms\n", "\n-3 atoms\n", 1))
def test_lammps_data(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("data") / "f.data"
    path.write_text(text)
    load_or_one_line(str(path), "lammps-data")


# --------------------------------------------------------------------------- LAMMPS dump

def _dump(n, d, cols, flags, fmt, frames=1):
    snap = (f"ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\n{n}\nITEM: BOX BOUNDS {flags}\n0 4.8\n"
            f"0 4.8\n0 4.8\nITEM: ATOMS {cols}\n" + "\n".join(_rows(n, d, n + 2, fmt)) + "\n")
    return snap * frames


DUMP_BASES = [
    _dump(6, 3, "id type x y z radius", "pp pp pp", "{k} 1 {x[0]} {x[1]} {x[2]} 0.5"),
    _dump(6, 3, "id type xs ys zs", "pp pp pp", "{k} 1 0.{k} 0.5 0.25"),
    _dump(5, 2, "id type xu yu zu diameter", "pp pp pp", "{k} 2 {x[0]} {x[1]} 0 1.0", 2),
]
VALID_DUMP = DUMP_BASES[0]


@profile(2)
@given(text=st.sampled_from(DUMP_BASES).flatmap(mutated))
@example(text=VALID_DUMP)
@example(text=VALID_DUMP.replace("NUMBER OF ATOMS\n6", "NUMBER OF ATOMS\n-1"))
def test_lammps_dump(tmp_path_factory, text):
    path = tmp_path_factory.mktemp("dump") / "f.dump"
    path.write_text(text)
    load_or_one_line(str(path), "lammps-dump")


# --------------------------------------------------------------------------- H5MD layouts

ARRAYS = st.one_of(
    st.tuples(st.integers(0, 6), st.integers(0, 4)).map(
        lambda s: np.random.default_rng(s[0] * 7 + s[1]).random(s) * 4),
    st.integers(0, 8).map(lambda n: np.random.default_rng(n).random(n) + 0.5),
    st.sampled_from([np.array(4.0), np.array([4.0, 4.0]), np.array([4.0, 4.0, 4.0]),
                     np.diag([4.0, 4.0]), np.diag([4.0, 4.0, 4.0]), np.array([[4.0, 1], [0, 4]]),
                     np.array([np.nan, 4.0]), np.array([0.0, 0.0]), np.zeros((0, 2)),
                     np.array([[4.0, 4.0], [4.0, 4.0]]), np.array(["a", "b"], dtype="S1"),
                     np.ones((2, 3, 2)), np.array([-4.0, -4.0])]))


@st.composite
def h5md_layout(draw):
    """{dataset path: array, or (group path, array) for a time series} and the box boundary."""
    n = draw(st.integers(0, 6))
    d = draw(st.sampled_from([2, 3, 1, 4]))
    rng = np.random.default_rng(n * 10 + d)
    items = {"position": rng.random((n, d)) * 4 if draw(st.integers(0, 3)) else draw(ARRAYS),
             "box/edges": draw(st.one_of(st.just(np.full(d, 4.0)), st.just(np.diag(np.full(
                 d, 4.0))), ARRAYS))}
    for name in ("species", "diameter", "radius"):
        if draw(st.booleans()):
            items[name] = draw(st.one_of(st.just(np.ones(n)), ARRAYS))
    series = {name for name in items if draw(st.integers(0, 3)) == 0}
    boundary = draw(st.sampled_from([None, ["periodic"] * d, ["none"] * d, ["periodic"], "x"]))
    group = draw(st.sampled_from(["all", "atoms", ""]))
    return items, series, boundary, group


@profile(2)
@given(layout=h5md_layout())
@example(layout=({"position": np.random.default_rng(1).random((4, 2)) * 4,
                  "box/edges": np.diag([4.0, 4.0]), "diameter": np.ones(4)}, set(),
                 ["periodic", "periodic"], "all"))
@example(layout=({"position": np.random.default_rng(1).random((4, 2)) * 4,
                  "box/edges": np.array([4.0, 4.0]), "diameter": np.float64(1.0)}, {"diameter"},
                 ["periodic", "periodic"], "all"))
@example(layout=({"position": np.random.default_rng(1).random((4, 3)) * 4,
                  "box/edges": np.array([4.0, 4.0, 4.0]), "species": np.int64(0)}, set(),
                 None, "all"))
def test_h5md(tmp_path_factory, layout):
    items, series, boundary, group = layout
    path = tmp_path_factory.mktemp("h5md") / "f.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group(f"particles/{group}" if group else "particles")
        for name, arr in items.items():
            if name in series:
                g.create_dataset(f"{name}/value", data=np.asarray(arr)[None])
            else:
                g.create_dataset(name, data=arr)
        if boundary is not None and "box" in g:
            g["box"].attrs["boundary"] = np.array(boundary, dtype="S")
    load_or_one_line(str(path), "h5md")


# --------------------------------------------------------------------------- through the command

@profile(0.5)
@given(text=st.sampled_from(XYZ_BASES).flatmap(mutated))
def test_import_command_is_one_line_or_a_packing_file(shared_tmp, text):
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    src = os.path.join(shared_tmp, "fuzz-import.xyz")
    out = os.path.join(shared_tmp, "fuzz-import.h5")
    if comm.Get_rank() == 0:
        with open(src, "w") as fh:
            fh.write(text)
        if os.path.exists(out):
            os.remove(out)
    comm.Barrier()
    rc, _, err = run_cli(["import", src, "--out", out, "-q"])
    assert "Traceback" not in err, err
    if rc == 0:
        assert_valid(read_packing(out))
    elif comm.Get_rank() == 0:
        lines = [ln for ln in err.splitlines() if ln.startswith("parjam: error:")]
        assert len(lines) == 1, err
    comm.Barrier()


def xyz_text():
    return st.sampled_from(XYZ_BASES).flatmap(mutated)


def data_text():
    return st.sampled_from(DATA_BASES).flatmap(mutated)


def dump_text():
    return st.sampled_from(DUMP_BASES).flatmap(mutated)
