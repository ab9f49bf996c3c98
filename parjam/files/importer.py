"""Configurations made elsewhere (LAMMPS, jax-md, HOOMD, ASE, an experiment) as parjam packings:
extended XYZ, LAMMPS data and dump files, and H5MD files of other programs.

Each reader returns positions, diameters, species and the box edges of a periodic cubic (3D)
or square (2D) box, in the file's length unit; :func:`load` validates them and rescales every
length by one factor so that the smallest diameter is 1 (parjam's unit sigma, in which the
energy window of the phi_c search and --ftol are set).  Nothing is guessed silently: a file
without diameters needs ``diameters`` (one per species or LAMMPS type), a triclinic or
non-cubic box, a missing column or a malformed line is a one-line ParjamError naming the file
and the line.
"""

import os
import re

import h5py
import numpy as np

from parjam.files import h5md
from parjam.errors import ParjamError
from parjam.files.h5md import read_packing
from parjam.net.system import Packing

FORMATS = ("extxyz", "lammps-data", "lammps-dump", "h5md")
EXTENSIONS = {".xyz": "extxyz", ".extxyz": "extxyz", ".data": "lammps-data",
              ".lmp": "lammps-data", ".lammps": "lammps-data", ".dump": "lammps-dump",
              ".lammpstrj": "lammps-dump", ".h5": "h5md", ".h5md": "h5md", ".hdf5": "h5md"}
MAX_BYTES = 4 << 30  # a text file larger than this is refused before it is read


class Raw:
    """What a reader found, before validation (lengths in the file's unit)."""

    def __init__(self, pos, diam, species, edges, fmt, alpha=None):
        self.pos, self.diam, self.species, self.edges = pos, diam, species, edges
        self.fmt, self.alpha = fmt, alpha


def detect_format(path, fmt=None):
    if fmt is not None:
        if fmt not in FORMATS:
            raise ParjamError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
        return fmt
    ext = os.path.splitext(path)[1].lower()
    if ext in EXTENSIONS:
        return EXTENSIONS[ext]
    raise ParjamError(f"{path}: cannot tell the format from the extension {ext or '(none)'}; "
                      f"give --format ({', '.join(FORMATS)})")


def load(path, fmt=None, diameters=None, dim=None, alpha=2.0):
    """A validated parjam Packing from a foreign file (module doc); ``meta`` records the source,
    its format and the length scale applied (new length = old length * length_scale)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ParjamError(f"{path}: no such file")
    fmt = detect_format(path, fmt)
    if fmt != "h5md" and os.path.getsize(path) > MAX_BYTES:
        raise ParjamError(f"{path}: {os.path.getsize(path)} bytes: too large to import")
    reader = {"extxyz": read_extxyz, "lammps-data": read_lammps_data,
              "lammps-dump": read_lammps_dump, "h5md": read_h5md}[fmt]
    try:
        raw = reader(path, dim)
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise ParjamError(f"{path}: not a readable {fmt} file ({exc})") from None
    pos, edges = np.asarray(raw.pos, float), np.atleast_1d(np.asarray(raw.edges, float))
    n, d = pos.shape
    species = (np.zeros(n, np.int32) if raw.species is None
               else np.asarray(raw.species, np.int64).astype(np.int32))
    diam = raw.diam
    if diam is None:
        diam = _diameters_by_species(path, species, diameters)
    elif diameters:
        raise ParjamError(f"{path}: the file gives diameters: --diameters is not needed")
    diam = np.asarray(diam, float)
    _check(path, pos, diam, edges)
    scale = 1.0 / float(diam.min())
    alpha = raw.alpha if raw.alpha is not None else alpha
    pack = h5md.validated_packing(path, pos * scale, diam * scale, edges * scale,
                                {"alpha": alpha})  # wraps into the box, refuses duplicates
    pack.meta = {"species": species, "source": os.path.abspath(path), "source_format": fmt,
                 "length_scale": scale}
    return pack


def _diameters_by_species(path, species, diameters):
    kinds = np.unique(species)
    if not diameters:
        if len(kinds) == 1:
            return np.ones(len(species))
        raise ParjamError(f"{path}: the file gives no diameters for its {len(kinds)} species "
                          f"({', '.join(str(k) for k in kinds)}): give --diameters, one per "
                          f"species in increasing order")
    if len(diameters) != len(kinds):
        raise ParjamError(f"{path}: --diameters gives {len(diameters)} values for "
                          f"{len(kinds)} species ({', '.join(str(k) for k in kinds)})")
    table = dict(zip(kinds.tolist(), diameters))
    return np.array([table[s] for s in species.tolist()], dtype=float)


def _check(path, pos, diam, edges):
    n, d = pos.shape
    if d not in (2, 3):
        raise ParjamError(f"{path}: positions must have 2 or 3 components, got {d}")
    if n < 2:
        raise ParjamError(f"{path}: a packing needs at least 2 particles, got {n}")
    if diam.shape != (n,):
        raise ParjamError(f"{path}: {len(diam)} diameters for {n} particles")
    for name, arr in (("positions", pos), ("diameters", diam), ("box edges", edges)):
        if not np.all(np.isfinite(arr)):
            raise ParjamError(f"{path}: {name} contain NaN or inf")
    if np.any(diam <= 0):
        raise ParjamError(f"{path}: diameters must be positive")
    if edges.shape != (d,) or edges[0] <= 0 or not np.allclose(edges, edges[0], rtol=1e-9):
        raise ParjamError(f"{path}: parjam needs a cubic (square) periodic box, got edges "
                          f"{edges.tolist()}")


# --- extended XYZ ------------------------------------------------------------------------------

_KEYVAL = re.compile(r'(\w+)\s*=\s*("[^"]*"|\S+)')


def read_extxyz(path, dim=None):
    """The last frame of an extended XYZ file (ASE, OVITO, parjam export): Lattice (orthogonal),
    Properties with pos and radius or diameter (else --diameters), species/type, pbc; a 2D
    packing has pbc="T T F" or dimension=2 (or ``dim``)."""
    with open(path) as fh:
        lines = fh.read().splitlines()
    frames, k = [], 0
    while k < len(lines):
        if not lines[k].strip():
            k += 1
            continue
        try:
            n = int(lines[k].split()[0])
        except ValueError:
            raise ValueError(f"line {k + 1}: expected the number of particles, got "
                             f"{lines[k][:40]!r}") from None
        if n < 0 or k + 2 + n > len(lines):
            raise ValueError(f"line {k + 1}: {n} particles announced, the file ends before")
        frames.append(k)
        k += 2 + n
    if not frames:
        raise ValueError("no frame")
    k = frames[-1]
    n = int(lines[k].split()[0])
    info = {key: val.strip('"') for key, val in _KEYVAL.findall(lines[k + 1])}
    if "Lattice" not in info:
        raise ValueError(f"line {k + 2}: no Lattice (parjam needs the periodic box)")
    cell = np.array(info["Lattice"].split(), float)
    if cell.shape != (9,):
        raise ValueError(f"line {k + 2}: Lattice needs 9 numbers")
    cell = cell.reshape(3, 3)
    if np.any(np.abs(cell - np.diag(np.diag(cell))) > 1e-12 * np.abs(cell).max()):
        raise ValueError(f"line {k + 2}: a triclinic Lattice; parjam needs a cubic box")
    pbc = info.get("pbc", "T T T").split()
    d = dim or int(info.get("dimension", 2 if pbc[2:] in (["F"], ["False"], ["0"]) else 3))
    cols = _properties(info.get("Properties", "species:S:1:pos:R:3"), k + 2)
    rows = [lines[k + 2 + j].split() for j in range(n)]
    width = sum(c for _, _, c in cols.values())
    for j, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"line {k + 3 + j}: {len(row)} columns, Properties give {width}")
    if "pos" not in cols:
        raise ValueError(f"line {k + 2}: Properties has no pos")
    table = np.array(rows, dtype=object)

    def column(name, kind=float):
        start, _, count = cols[name]
        return table[:, start:start + count].astype(kind)

    pos = column("pos")[:, :d]
    diam = None
    if "radius" in cols:
        diam = 2.0 * column("radius")[:, 0]
    elif "diameter" in cols:
        diam = column("diameter")[:, 0]
    species = None
    for name in ("type", "species", "Z"):
        if name in cols:
            species = _species_ids(column(name, str)[:, 0])
            break
    alpha = float(info["alpha"]) if "alpha" in info else None
    return Raw(pos, diam, species, np.diag(cell)[:d], "extxyz", alpha)


def _properties(text, line):
    parts = text.split(":")
    if len(parts) % 3:
        raise ValueError(f"line {line}: malformed Properties {text!r}")
    cols, start = {}, 0
    for name, kind, count in zip(parts[::3], parts[1::3], parts[2::3]):
        cols[name] = (start, kind, int(count))
        start += int(count)
    return cols


def _species_ids(labels):
    """Integer species: the labels themselves when they are integers, else their rank among the
    sorted distinct labels (so "A", "B" -> 0, 1)."""
    try:
        return np.array([int(x) for x in labels], dtype=np.int64)
    except ValueError:
        kinds = sorted(set(labels))
        return np.array([kinds.index(x) for x in labels], dtype=np.int64)


# --- LAMMPS ------------------------------------------------------------------------------------

def read_lammps_data(path, dim=None):
    """A LAMMPS data file (write_data): header counts and box, the Atoms section in atom_style
    atomic (id type x y z) or sphere (id type diameter density x y z), image flags allowed.  2D
    (``dimension 2`` in LAMMPS) when ``dim`` is 2 or every z is equal."""
    with open(path) as fh:
        lines = [ln.split("#", 1) for ln in fh.read().splitlines()]
    n, bounds, k, style = None, {}, 1, None
    tilt = None
    while k < len(lines):
        body = lines[k][0].strip()
        if not body:
            k += 1
            continue
        words = body.split()
        if len(words) == 2 and words[1] == "atoms":
            n = int(words[0])
        elif len(words) == 4 and words[2][1:] == "lo" and words[3][1:] == "hi":
            bounds[words[2][0]] = (float(words[0]), float(words[1]))
        elif words[-3:] == ["xy", "xz", "yz"]:
            tilt = [float(w) for w in words[:3]]
        elif words[0] == "Atoms":
            style = lines[k][1].strip().split()[0] if len(lines[k]) > 1 and \
                lines[k][1].strip() else None
            k += 1
            break
        elif words[0][0].isalpha():  # another section before Atoms (Masses, ...)
            pass
        k += 1
    else:
        raise ValueError("no Atoms section")
    if n is None:
        raise ValueError("no 'N atoms' line in the header")
    if tilt is not None and any(tilt):
        raise ValueError("a triclinic box; parjam needs a cubic box")
    if set(bounds) != {"x", "y", "z"}:
        raise ValueError("the header needs xlo xhi, ylo yhi and zlo zhi")
    rows = []
    while k < len(lines) and len(rows) < n:
        body = lines[k][0].split()
        if body:
            rows.append((k + 1, body))
        k += 1
    if len(rows) < n:
        raise ValueError(f"the Atoms section holds {len(rows)} lines for {n} atoms")
    width = {len(r) for _, r in rows}
    if len(width) != 1:
        line = next(ln for ln, r in rows if len(r) != len(rows[0][1]))
        raise ValueError(f"line {line}: not as many columns as the first atom")
    width = width.pop()
    style = style or {5: "atomic", 8: "atomic", 7: "sphere", 10: "sphere"}.get(width)
    layout = {"atomic": (None, 2), "sphere": (2, 4)}
    if style not in layout:
        raise ValueError(f"atom_style {style or '(unknown, ' + str(width) + ' columns)'}: "
                         f"parjam reads atomic and sphere")
    dcol, xcol = layout[style]
    data = np.array([r for _, r in rows], dtype=float)
    order = np.argsort(data[:, 0], kind="stable")
    data = data[order]
    lo = np.array([bounds[a][0] for a in "xyz"])
    edges = np.array([bounds[a][1] - bounds[a][0] for a in "xyz"])
    pos = data[:, xcol:xcol + 3] - lo
    d = _lammps_dim(pos, dim)
    diam = data[:, dcol] if dcol is not None else None
    return Raw(pos[:, :d], diam, data[:, 1].astype(np.int64), edges[:d], "lammps-data")


def _lammps_dim(pos, dim):
    if dim is not None:
        return dim
    return 2 if np.ptp(pos[:, 2]) == 0.0 else 3


def read_lammps_dump(path, dim=None):
    """The last snapshot of a LAMMPS text dump (dump atom/custom): ITEM: BOX BOUNDS (orthogonal,
    periodic), ITEM: ATOMS with id, type, x y z (or xs ys zs scaled, or xu yu zu) and radius or
    diameter when present."""
    with open(path) as fh:
        lines = fh.read().splitlines()
    starts = [k for k, ln in enumerate(lines) if ln.startswith("ITEM: TIMESTEP")]
    if not starts:
        raise ValueError("no 'ITEM: TIMESTEP': not a LAMMPS dump")
    k = starts[-1]
    n = edges = lo = cols = None
    while k < len(lines):
        ln = lines[k]
        if ln.startswith("ITEM: NUMBER OF ATOMS"):
            n = int(lines[k + 1])
        elif ln.startswith("ITEM: BOX BOUNDS"):
            flags = ln.split()[3:]
            if "xy" in flags:
                raise ValueError(f"line {k + 1}: a triclinic box; parjam needs a cubic box")
            if any(f != "pp" for f in flags):
                raise ValueError(f"line {k + 1}: boundaries {' '.join(flags)}; parjam needs "
                                 f"periodic (pp pp pp)")
            b = np.array([lines[k + 1 + a].split()[:2] for a in range(3)], dtype=float)
            lo, edges = b[:, 0], b[:, 1] - b[:, 0]
        elif ln.startswith("ITEM: ATOMS"):
            cols = ln.split()[2:]
            k += 1
            break
        k += 1
    if n is None or edges is None or cols is None:
        raise ValueError("the last snapshot lacks NUMBER OF ATOMS, BOX BOUNDS or ATOMS")
    rows = [lines[k + j].split() for j in range(n)]
    for j, row in enumerate(rows):
        if len(row) != len(cols):
            raise ValueError(f"line {k + j + 1}: {len(row)} columns, ITEM: ATOMS names "
                             f"{len(cols)}")
    data = np.array(rows, dtype=float)
    if "id" in cols:
        data = data[np.argsort(data[:, cols.index("id")], kind="stable")]
    for names, scaled in ((("x", "y", "z"), False), (("xu", "yu", "zu"), False),
                          (("xs", "ys", "zs"), True)):
        if all(c in cols for c in names):
            pos = data[:, [cols.index(c) for c in names]]
            pos = pos * edges if scaled else pos - lo
            break
    else:
        raise ValueError("ITEM: ATOMS has no x y z (or xs ys zs, xu yu zu) columns")
    diam = None
    if "radius" in cols:
        diam = 2.0 * data[:, cols.index("radius")]
    elif "diameter" in cols:
        diam = data[:, cols.index("diameter")]
    species = data[:, cols.index("type")].astype(np.int64) if "type" in cols else None
    d = _lammps_dim(pos, dim)
    return Raw(pos[:, :d], diam, species, edges[:d], "lammps-dump")


# --- H5MD of other programs --------------------------------------------------------------------

def read_h5md(path, dim=None):
    """The last frame of the first particle group of an H5MD file: position (time series or
    fixed), box edges (time series or fixed; a (d, d) matrix must be diagonal), species,
    diameter or radius (fixed or time series) when present."""
    if not h5py.is_hdf5(path):
        raise ValueError("not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            if "particles" not in f or not len(f["particles"]):
                raise ValueError("no /particles group: not an H5MD particle file")
            name = sorted(f["particles"])[0]
            g = f["particles"][name]
            pos = _last_frame(g, "position", 2)
            if pos is None:
                raise ValueError(f"/particles/{name} has no position")
            if "box" not in g or "edges" not in g["box"]:
                raise ValueError(f"/particles/{name}/box has no edges (parjam needs a periodic "
                                 f"box)")
            boundary = [b.decode() if isinstance(b, bytes) else str(b)
                        for b in np.atleast_1d(g["box"].attrs.get("boundary", ["periodic"]))]
            if any(b != "periodic" for b in boundary):
                raise ValueError(f"box boundary {boundary}: parjam needs a periodic box")
            edges = _last_frame(g["box"], "edges", 1)
            if edges.ndim == 2:
                if np.any(edges - np.diag(np.diag(edges))):
                    raise ValueError("a triclinic box; parjam needs a cubic box")
                edges = np.diag(edges)
            species = _last_frame(g, "species", 1)
            diam = _last_frame(g, "diameter", 1)
            if diam is None:
                radius = _last_frame(g, "radius", 1)
                diam = None if radius is None else 2.0 * radius
            alpha = None
            if "parameters" in f and "alpha" in f["parameters"].attrs:
                alpha = float(np.asarray(f["parameters"].attrs["alpha"]).reshape(()))
    except OSError as exc:
        raise ValueError(f"unreadable HDF5 ({exc})") from None
    if pos.ndim != 2:
        raise ValueError(f"positions of shape {pos.shape}")
    d = dim or pos.shape[1]
    return Raw(pos[:, :d], diam, species, np.atleast_1d(edges)[:d], "h5md", alpha)


def _last_frame(g, name, ndim):
    """A fixed dataset or the last frame of a time series; None if absent."""
    if name not in g:
        return None
    obj = g[name]
    if isinstance(obj, h5py.Group):
        if "value" not in obj:
            raise ValueError(f"{obj.name} has no value")
        obj = obj["value"]  # a time series: the first axis counts the frames
        if obj.dtype.kind not in "biuf" or obj.ndim < 1:
            raise ValueError(f"{obj.name} is not a numeric time series")
        if obj.shape[0] == 0:
            raise ValueError(f"{obj.name} holds no frame")
        return np.asarray(obj[-1], dtype=float)
    if obj.dtype.kind not in "biuf":
        raise ValueError(f"{obj.name} is not numeric")
    arr = np.asarray(obj[()], dtype=float)
    return arr[-1] if arr.ndim == ndim + 1 else arr


def from_file(path, alpha):
    """A packing to start ``pack --from FILE`` with: parjam's own file (or any H5MD file
    read_packing accepts), the potential exponent set to ``alpha``."""
    pack = read_packing(path)
    meta = {"species": pack.meta.get("species"), "source": os.path.abspath(path)}
    return Packing(pack.pos.copy(), pack.diam.copy(), pack.L, alpha, pack.eps, meta)

