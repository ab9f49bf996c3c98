"""Configurations made elsewhere (LAMMPS, jax-md, HOOMD, ASE, OVITO, an experiment) as parjam
packings: extended XYZ, LAMMPS data and dump files (parjam.files.lammpsio), GSD files and H5MD
files of other programs.

Each reader returns positions, diameters, species and the box edges of a periodic cubic (3D)
or square (2D) box, in the file's length unit; :func:`load` validates them and rescales every
length by one factor so that the smallest diameter is 1 (parjam's unit sigma, in which the
energy window of the phi_c search and --ftol are set).  Nothing is guessed silently: a file
without diameters needs ``diameters`` (one per species or LAMMPS type); a triclinic,
non-cubic or non-periodic box, a missing column, a malformed line, or a volume fraction that
``parjam pack --from`` refuses is a one-line ParjamError naming the file and the line.
"""

import os
import re

import h5py
import numpy as np

from parjam.files import export, h5md, lammpsio
from parjam.errors import ParjamError
from parjam.files.formats import IMPORT_EXTENSIONS, IMPORT_FORMATS
from parjam.files.h5md import read_packing
from parjam.net.system import Packing

FORMATS, EXTENSIONS = IMPORT_FORMATS, IMPORT_EXTENSIONS
ATOM_STYLES = lammpsio.STYLES
MAX_BYTES = 4 << 30  # a text file larger than this is refused before it is read
PHI_MIN = 0.05  # the volume fractions `parjam pack` starts from (its --phi-start range)


def phi_max(d):
    """The largest volume fraction ``parjam pack`` starts from (its --phi-start range): 1 in
    3D; 1.5 in 2D, where bidisperse discs overlap more before a box is full."""
    return 1.0 + 0.5 * (d == 2)


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


def load(path, fmt=None, diameters=None, dim=None, alpha=2.0, atom_style=None):
    """A validated parjam Packing from a foreign file (module doc); ``meta`` records the source,
    its format and the length scale applied (new length = old length * length_scale)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ParjamError(f"{path}: no such file")
    fmt = detect_format(path, fmt)
    if atom_style is not None and fmt != "lammps-data":
        raise ParjamError(f"{path}: --atom-style is for LAMMPS data files, this is {fmt}")
    if fmt not in ("h5md", "gsd") and os.path.getsize(path) > MAX_BYTES:
        raise ParjamError(f"{path}: {os.path.getsize(path)} bytes: too large to import")
    try:
        if fmt == "lammps-data":
            raw = read_lammps_data(path, dim, atom_style)
        else:
            raw = {"extxyz": read_extxyz, "lammps-dump": read_lammps_dump, "gsd": read_gsd,
                   "h5md": read_h5md}[fmt](path, dim)
    except (ValueError, IndexError, UnicodeDecodeError) as exc:
        raise ParjamError(f"{path}: not a readable {fmt} file ({exc})") from None
    pos, edges = np.asarray(raw.pos, float), np.atleast_1d(np.asarray(raw.edges, float))
    n, d = pos.shape
    species = (np.zeros(n, np.int32) if raw.species is None
               else np.asarray(raw.species, np.int64).astype(np.int32))
    if species.shape != (n,):
        raise ParjamError(f"{path}: species of shape {species.shape} for {n} particles (one "
                          f"per particle)")
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
    _check_phi(path, pack)
    pack.meta = {"species": species, "source": os.path.abspath(path), "source_format": fmt,
                 "length_scale": scale}
    return pack


def _check_phi(path, pack):
    """The volume fraction must be one ``parjam pack --from`` starts from (commands/pack.py's
    range of --phi-start): refused here, before a file is written that it would refuse."""
    phi, top = pack.phi, phi_max(pack.d)
    if not PHI_MIN <= phi < top:
        why = ("the spheres' volume exceeds the box's: the overlaps are too large for a "
               "packing parjam can jam" if phi >= top else "too dilute to start a packing from")
        raise ParjamError(f"{path}: volume fraction phi = {phi:.6g} lies outside "
                          f"[{PHI_MIN:g}, {top:g}) in {pack.d}D ({why}); `parjam pack --from` "
                          f"starts only from that range")


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
        got = f"{diam.size} diameters" if diam.ndim == 1 else f"diameters of shape {diam.shape}"
        raise ParjamError(f"{path}: {got} for {n} particles (one per particle)")
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
    pbc = _pbc(info.get("pbc", "T T T"), k + 2)
    d = _xyz_dimension(info, pbc, dim, k + 2)
    cols = _properties(info.get("Properties", "species:S:1:pos:R:3"), k + 2)
    rows = [lines[k + 2 + j].split() for j in range(n)]
    width = sum(c for _, _, c in cols.values())
    for j, row in enumerate(rows):
        if len(row) != width:
            raise ValueError(f"line {k + 3 + j}: {len(row)} columns, Properties give {width}")
    if "pos" not in cols or cols["pos"][2] not in (2, 3):
        raise ValueError(f"line {k + 2}: Properties has no pos of 2 or 3 components")
    table = np.array(rows, dtype=object).reshape(n, width)

    def column(name, kind=float):
        start, _, count = cols[name]
        return table[:, start:start + count].astype(kind)

    pos = column("pos")
    if pos.shape[1] < d:
        raise ValueError(f"line {k + 2}: {d}D, but pos has {pos.shape[1]} components")
    if d == 2 and pos.shape[1] == 3 and n and np.ptp(pos[:, 2]) != 0.0:
        raise ValueError(f"line {k + 2}: a 2D packing (pbc or dimension) whose z coordinates "
                         f"vary: a 3D configuration that is not periodic along z?")
    pos = pos[:, :d]
    diam = None
    if "radius" in cols:
        diam = 2.0 * column("radius")[:, 0]
    elif "diameter" in cols:
        diam = column("diameter")[:, 0]
    species = None
    for name in ("species", "type", "Z"):
        if name in cols:
            species = _species_ids(column(name, str)[:, 0])
            break
    alpha = float(info["alpha"]) if "alpha" in info else None
    return Raw(pos, diam, species, np.diag(cell)[:d], "extxyz", alpha)


_TRUE, _FALSE = ("t", "true", "1"), ("f", "false", "0")


def _pbc(text, line):
    """The three periodicity flags of an extended XYZ header."""
    words = text.lower().split()
    if len(words) != 3 or any(w not in _TRUE + _FALSE for w in words):
        raise ValueError(f'line {line}: pbc="{text}": expected three flags T or F')
    return [w in _TRUE for w in words]


def _xyz_dimension(info, pbc, dim, line):
    """2 or 3: ``dim`` (--dim), else the header's ``dimension``, else 2 when z is not
    periodic; every direction of the packing must be periodic."""
    d = None
    if "dimension" in info:
        try:
            d = int(info["dimension"])
        except ValueError:
            d = None
        if d not in (2, 3):
            raise ValueError(f"line {line}: dimension={info['dimension']}: parjam packings are "
                             f"2D or 3D")
        if dim is not None and dim != d:
            raise ValueError(f"line {line}: the file says dimension={d}, --dim says {dim}")
    d = dim or d or (3 if pbc[2] else 2)
    flat = [a for a, p in zip("xyz"[:d], pbc) if not p]
    if flat:
        raise ValueError(f'line {line}: not periodic along {" and ".join(flat)} (pbc='
                         f'"{" ".join("T" if p else "F" for p in pbc)}"): parjam needs a '
                         f'periodic box in every direction of a {d}D packing')
    return d


def _properties(text, line):
    parts = text.split(":")
    if len(parts) % 3:
        raise ValueError(f"line {line}: malformed Properties {text!r}")
    cols, start = {}, 0
    for name, kind, count in zip(parts[::3], parts[1::3], parts[2::3]):
        if not count.isdigit() or int(count) < 1:
            raise ValueError(f"line {line}: Properties column {name} has {count!r} components")
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

def read_lammps_data(path, dim=None, atom_style=None):
    """A LAMMPS data file (parjam.files.lammpsio.read_data: atomic, charge, molecular, full or
    sphere; image flags allowed).  2D (``dimension 2`` in LAMMPS) when ``dim`` is 2 or every z
    is equal."""
    pos, diam, types, edges = lammpsio.read_data(path, atom_style)
    d = _lammps_dim(pos, dim)
    return Raw(pos[:, :d], diam, types, edges[:d], "lammps-data")


def _lammps_dim(pos, dim):
    if dim is not None:
        return dim
    return 2 if np.ptp(pos[:, 2]) == 0.0 else 3


def read_lammps_dump(path, dim=None):
    """The last snapshot of a LAMMPS text dump (parjam.files.lammpsio.read_dump): id, type,
    x y z (or xs ys zs scaled, or xu yu zu), radius or diameter when present."""
    pos, diam, types, edges, periodic = lammpsio.read_dump(path)
    d = _lammps_dim(pos, dim)
    if not all(periodic[:d]):
        raise ValueError(f"boundaries {' '.join('pp' if p else 'not pp' for p in periodic)}: "
                         f"parjam needs a periodic box along every axis of a {d}D packing")
    return Raw(pos[:, :d], diam, types, edges[:d], "lammps-dump")


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
            edges = _box_edges(g["box"], pos.shape[-1])
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


def _box_edges(box, d):
    """The box edges of the last frame: a vector (d,) or a matrix (d, d), fixed or a time
    series (T, d) or (T, d, d); a matrix must be diagonal (H5MD allows both forms)."""
    if "edges" not in box:
        raise ValueError(f"{box.name} has no edges (parjam needs a periodic box)")
    obj = box["edges"]
    series = isinstance(obj, h5py.Group)
    arr = _last_frame(box, "edges", None)
    if arr.shape == ():  # one number: a cube (older writers)
        arr = np.full(d, float(arr))
    if not series and arr.shape not in ((d,), (d, d)):
        raise ValueError(f"{obj.name} of shape {arr.shape}: expected ({d},) or ({d}, {d})")
    if series and arr.shape not in ((d,), (d, d)):
        raise ValueError(f"{obj.name}/value frames of shape {arr.shape}: expected ({d},) or "
                         f"({d}, {d})")
    if arr.ndim == 2:
        if np.any(arr - np.diag(np.diag(arr))):
            raise ValueError(f"{obj.name}: a triclinic box (off-diagonal edges); parjam needs "
                             f"a cubic box")
        arr = np.diag(arr).copy()
    return arr


def _last_frame(g, name, ndim):
    """A fixed dataset or the last frame of a time series; None if absent.  A fixed dataset
    with ``ndim + 1`` axes is read as frames (``ndim`` None: never)."""
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
    return arr[-1] if ndim is not None and arr.ndim == ndim + 1 and len(arr) else arr


# --- GSD (HOOMD-blue) ---------------------------------------------------------------------------

def read_gsd(path, dim=None):
    """The last frame of a GSD file (HOOMD schema, the ``gsd`` package): box (Lx, Ly, Lz with
    zero tilts; 2D when ``dimensions`` is 2), positions centred on the origin, typeid as the
    species, diameter when the file has it (the gsd package would otherwise return 1 for every
    particle: such a file needs --diameters like any file without diameters).  The exact
    float64 positions and diameters of ``parjam export`` (``log/parjam/*``) replace the
    single-precision arrays when they round to them; otherwise the single-precision values are
    used (another program rewrote the particles)."""
    try:
        import gsd.fl
        import gsd.hoomd
    except ImportError:
        raise ParjamError(f"{path}: reading GSD files needs the gsd package (pip install "
                          f"gsd)") from None
    try:
        with gsd.fl.open(path, "r") as fl:
            frames = fl.nframes
            if frames == 0:
                raise ValueError("no frame")
            last = frames - 1
            has_diameter = any(fl.chunk_exists(frame=f, name="particles/diameter")
                               for f in {0, last})
        with gsd.hoomd.open(path, "r") as traj:
            frame = traj[-1]
    except (OSError, RuntimeError, KeyError) as exc:  # not a GSD file, damaged inside
        raise ValueError(f"unreadable GSD ({exc})") from None
    box = np.asarray(frame.configuration.box, float)
    dims = int(frame.configuration.dimensions)
    d = dim or (2 if dims == 2 or box[2] == 0 else 3)
    if np.any(box[3:] != 0):
        raise ValueError(f"a triclinic box (tilts {box[3:].tolist()}); parjam needs a cubic box")
    n = int(frame.particles.N)
    single = np.asarray(frame.particles.position, np.float32).reshape(n, 3)
    if d == 2 and n and np.ptp(single[:, 2]) != 0.0:
        raise ValueError("a 2D box whose z coordinates vary")
    edges = box[:d]
    log = frame.log or {}
    exact_edge = _exact(log, "parjam/box_edge", (1,))
    if exact_edge is not None and np.all(np.float32(exact_edge[0]) == np.float32(edges)):
        edges = np.full(d, exact_edge[0])
    pos = single[:, :d].astype(float) + edges / 2.0  # HOOMD's box is centred on the origin
    diam = np.asarray(frame.particles.diameter, np.float32) if has_diameter else None
    exact = _exact(log, "parjam/position", (n, 3))
    if exact is not None and np.array_equal(
            export.centred_single(exact, float(edges[0]))[:, :d], single[:, :d]):
        pos = exact[:, :d]
    if diam is not None:
        exact = _exact(log, "parjam/diameter", (n,))
        diam = exact if exact is not None and np.array_equal(exact.astype(np.float32), diam) \
            else diam.astype(float)
    species = np.asarray(frame.particles.typeid, np.int64)
    alpha = None
    if "parjam/alpha" in log:
        alpha = float(np.asarray(log["parjam/alpha"]).reshape(-1)[0])
    return Raw(pos, diam, species, edges, "gsd", alpha)


def _exact(log, key, shape):
    """The float64 array ``log[key]`` of ``parjam export`` if it has ``shape``, else None."""
    if key not in log:
        return None
    arr = np.asarray(log[key])
    if arr.shape != shape or arr.dtype.kind != "f":
        return None
    return arr.astype(float)


def from_file(path, alpha):
    """A packing to start ``pack --from FILE`` with: parjam's own file (or any H5MD file
    read_packing accepts), the potential exponent set to ``alpha``."""
    pack = read_packing(path)
    meta = {"species": pack.meta.get("species"), "source": os.path.abspath(path)}
    return Packing(pack.pos.copy(), pack.diam.copy(), pack.L, alpha, pack.eps, meta)

