"""LAMMPS data files and text dumps read for ``parjam import`` (parjam.files.importer).

Data files: the header's ``N atoms``, ``N atom types`` and box (``xlo xhi`` ..., or the
general-triclinic ``avec``/``bvec``/``cvec``/``abc origin`` lines that OVITO writes; a line of
boundary flags such as ``pp pp pp`` is accepted when every flag is periodic), then the Atoms
section in one of the layouts of ``LAYOUTS`` (image flags allowed).  The layout is the style
comment after ``Atoms`` (``Atoms # full``) or ``atom_style``; a bare ``Atoms`` header is read
only when exactly one layout of its column count fits the rows (integer ids, molecule ids and
types, types within 1 .. ``N atom types``, positive diameters): MDAnalysis writes ``id mol type
x y z`` under a bare header, which is molecular because its molecule column holds 0, never a
type.  When two layouts fit (7 columns: sphere or full) the file is refused and the style must
be named.

Dumps: the last snapshot; ``ITEM: BOX BOUNDS`` orthogonal, with zero tilts (``xy xz yz``),
or general triclinic (``abc origin``, OVITO's) with a diagonal cell; the boundary flags are
returned (OVITO writes ``pp pp ff`` for a 2D configuration: the importer needs ``pp`` along
the packing's own axes only).

Each reader returns (positions (N, 3) from the box's lower corner, diameters or None, integer
types or None, edges (3,)) in the file's units, and :func:`read_dump` the periodicity of each
axis; every problem is a ValueError naming the line.
"""

import numpy as np

#: atom_style -> column of the type, of the diameter (None: no diameters), of x, the columns
#: that must hold integers, and the number of columns without image flags
LAYOUTS = {
    "atomic": dict(type=1, diameter=None, x=2, ints=(0, 1), width=5),
    "charge": dict(type=1, diameter=None, x=3, ints=(0, 1), width=6),
    "molecular": dict(type=2, diameter=None, x=3, ints=(0, 1, 2), width=6),
    "full": dict(type=2, diameter=None, x=4, ints=(0, 1, 2), width=7),
    "sphere": dict(type=1, diameter=2, x=4, ints=(0, 1), width=7),
}
ALIASES = {"bond": "molecular", "angle": "molecular"}
STYLES = tuple(LAYOUTS) + tuple(ALIASES)
SECTIONS = ("Atoms", "Velocities", "Masses", "Bonds", "Angles", "Dihedrals", "Impropers",
            "Pair Coeffs", "PairIJ Coeffs", "Bond Coeffs", "Angle Coeffs", "Dihedral Coeffs",
            "Improper Coeffs", "Atom Type Labels", "Ellipsoids", "Lines", "Triangles",
            "Bodies")
MAX_ATOMS = 50_000_000  # as parjam.files.h5md.MAX_PARTICLES


def _count(text, what, line):
    try:
        n = int(text)
    except ValueError:
        raise ValueError(f"line {line}: '{text} {what}' is not a count") from None
    if n <= 0:
        raise ValueError(f"line {line}: {n} {what}: a packing needs particles")
    if n > MAX_ATOMS:
        raise ValueError(f"line {line}: {n} {what}: more than {MAX_ATOMS}")
    return n


def _flags_periodic(flags, line):
    if any(f != "pp" for f in flags):
        raise ValueError(f"line {line}: boundaries {' '.join(flags)}; parjam needs a periodic "
                         f"box (pp pp pp)")


def _is_flags(words):
    return len(words) == 3 and all(len(w) == 2 and set(w) <= set("pfsm") for w in words)


def _diagonal_cell(cell, line):
    """Edges of a cell (rows a, b, c) that must be orthogonal and aligned with x, y, z."""
    off = cell - np.diag(np.diag(cell))
    if np.any(np.abs(off) > 1e-12 * np.abs(cell).max()):
        raise ValueError(f"line {line}: a triclinic box; parjam needs a cubic box")
    return np.diag(cell).copy()


def read_data(path, style=None):
    """Module doc.  ``style`` (an atom_style) overrides the file's comment."""
    with open(path) as fh:
        lines = [ln.split("#", 1) for ln in fh.read().splitlines()]
    n = ntypes = None
    bounds, vecs, tilt, k = {}, {}, None, 1
    while k < len(lines):
        body = lines[k][0].strip()
        words = body.split()
        if not words:
            k += 1
            continue
        if words[0] in SECTIONS or body in SECTIONS:
            break
        if len(words) == 2 and words[1] == "atoms":
            n = _count(words[0], "atoms", k + 1)
        elif len(words) == 3 and words[1:] == ["atom", "types"]:
            ntypes = _count(words[0], "atom types", k + 1)
        elif len(words) == 4 and words[2][1:] == "lo" and words[3][1:] == "hi":
            bounds[words[2][0]] = (float(words[0]), float(words[1]))
        elif words[-3:] == ["xy", "xz", "yz"]:
            tilt = [float(w) for w in words[:3]]
        elif len(words) == 4 and words[3] in ("avec", "bvec", "cvec"):
            vecs[words[3]] = [float(w) for w in words[:3]]
        elif len(words) == 5 and words[3:] == ["abc", "origin"]:
            vecs["origin"] = [float(w) for w in words[:3]]
        elif _is_flags(words):
            _flags_periodic(words, k + 1)
        k += 1
    if n is None:
        raise ValueError("no 'N atoms' line in the header")
    if tilt is not None and any(tilt):
        raise ValueError("a triclinic box; parjam needs a cubic box")
    if vecs:
        if set(vecs) != {"avec", "bvec", "cvec", "origin"}:
            raise ValueError("the header needs avec, bvec, cvec and abc origin together")
        edges = _diagonal_cell(np.array([vecs["avec"], vecs["bvec"], vecs["cvec"]]), 1)
        lo = np.array(vecs["origin"])
    elif set(bounds) == {"x", "y", "z"}:
        lo = np.array([bounds[a][0] for a in "xyz"])
        edges = np.array([bounds[a][1] - bounds[a][0] for a in "xyz"])
    else:
        raise ValueError("the header needs xlo xhi, ylo yhi and zlo zhi")
    while k < len(lines) and lines[k][0].strip() != "Atoms":
        k += 1
    if k == len(lines):
        raise ValueError("no Atoms section")
    comment = lines[k][1].split() if len(lines[k]) > 1 else []
    header_line = k + 1
    k += 1
    rows = []
    while k < len(lines) and len(rows) < n:
        body = lines[k][0].split()
        if body:
            if body[0] in SECTIONS:
                break
            rows.append((k + 1, body))
        k += 1
    if len(rows) < n:
        raise ValueError(f"the Atoms section holds {len(rows)} lines for {n} atoms")
    width = len(rows[0][1])
    for line, r in rows:
        if len(r) != width:
            raise ValueError(f"line {line}: {len(r)} columns, the first atom has {width}")
    try:
        data = np.array([r for _, r in rows], dtype=float)
    except ValueError:
        bad = next(line for line, r in rows if not _floats(r))
        raise ValueError(f"line {bad}: not a row of numbers") from None
    name = _layout(style or (comment[0] if comment else None), data, width, ntypes, header_line)
    lay = LAYOUTS[name]
    problem = _misfit(lay, data, ntypes)
    if problem:
        raise ValueError(f"Atoms # {name}: {problem}")
    data = data[np.argsort(data[:, 0], kind="stable")]
    pos = data[:, lay["x"]:lay["x"] + 3] - lo
    diam = data[:, lay["diameter"]] if lay["diameter"] is not None else None
    return pos, diam, data[:, lay["type"]].astype(np.int64), edges


def _floats(row):
    try:
        [float(x) for x in row]
        return True
    except ValueError:
        return False


def _layout(style, data, width, ntypes, line):
    """The atom_style of the Atoms section (module doc)."""
    if style is not None:
        name = ALIASES.get(style, style)
        if name not in LAYOUTS:
            raise ValueError(f"line {line}: atom_style {style}: parjam reads "
                             f"{', '.join(STYLES)}")
        if width not in (LAYOUTS[name]["width"], LAYOUTS[name]["width"] + 3):
            raise ValueError(f"line {line}: atom_style {name} has {LAYOUTS[name]['width']} "
                             f"columns (+3 image flags), the rows have {width}")
        return name
    candidates = [s for s, lay in LAYOUTS.items() if width in (lay["width"], lay["width"] + 3)]
    if not candidates:
        raise ValueError(f"line {line}: {width} columns fit no atom_style parjam reads "
                         f"({', '.join(STYLES)})")
    fits = [s for s in candidates if _misfit(LAYOUTS[s], data, ntypes) is None]
    if len(fits) == 1:
        return fits[0]
    if not fits:
        raise ValueError(f"line {line}: a bare Atoms header and {width} columns that fit none "
                         f"of {', '.join(candidates)}: name the style ('Atoms # STYLE' or "
                         f"--atom-style)")
    raise ValueError(f"line {line}: a bare Atoms header and {width} columns: "
                     f"{' or '.join(fits)}? name the style ('Atoms # STYLE' or --atom-style)")


def _misfit(lay, data, ntypes):
    """Why the rows do not fit a layout, or None."""
    for col in lay["ints"]:
        if not np.all(data[:, col] == np.round(data[:, col])):
            return f"column {col + 1} must hold integers"
    types = data[:, lay["type"]]
    top = ntypes if ntypes is not None else np.inf
    if np.any(types < 1) or np.any(types > top):
        return (f"types (column {lay['type'] + 1}) must lie in 1 .. "
                f"{ntypes if ntypes is not None else 'N'}")
    if lay["diameter"] is not None and np.any(data[:, lay["diameter"]] <= 0):
        return f"diameters (column {lay['diameter'] + 1}) must be positive"
    if len(data[0]) == lay["width"] + 3:
        flags = data[:, lay["width"]:]
        if not np.all(flags == np.round(flags)):
            return "image flags (the last 3 columns) must be integers"
    return None


def read_dump(path):
    """Module doc: the last snapshot of a text dump (dump atom/custom)."""
    with open(path) as fh:
        lines = fh.read().splitlines()
    starts = [k for k, ln in enumerate(lines) if ln.startswith("ITEM: TIMESTEP")]
    if not starts:
        raise ValueError("no 'ITEM: TIMESTEP': not a LAMMPS dump")
    k = starts[-1]
    n = edges = lo = cols = periodic = None
    while k < len(lines):
        ln = lines[k]
        if ln.startswith("ITEM: NUMBER OF ATOMS"):
            if k + 1 >= len(lines):
                raise ValueError(f"line {k + 1}: the file ends after NUMBER OF ATOMS")
            n = _count(lines[k + 1].strip(), "atoms", k + 2)
        elif ln.startswith("ITEM: BOX BOUNDS"):
            edges, lo, periodic = _dump_box(lines, k)
        elif ln.startswith("ITEM: ATOMS"):
            cols = ln.split()[2:]
            k += 1
            break
        k += 1
    if n is None or edges is None or cols is None:
        raise ValueError("the last snapshot lacks NUMBER OF ATOMS, BOX BOUNDS or ATOMS")
    if k + n > len(lines):
        raise ValueError(f"line {k + 1}: {n} atoms announced, the file ends before")
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
    types = None
    if "type" in cols:
        types = data[:, cols.index("type")]
        if not np.all(types == np.round(types)):
            raise ValueError("the type column must hold integers")
        types = types.astype(np.int64)
    return pos, diam, types, edges, periodic


def _dump_box(lines, k):
    """(edges, lower corner, periodic along x, y, z) of an ITEM: BOX BOUNDS line at index k
    and the 3 lines below."""
    words = lines[k].split()[3:]
    flags = [w for w in words if _is_flags([w] * 3)]
    kind = [w for w in words if w not in flags]
    if len(flags) not in (0, 3):
        raise ValueError(f"line {k + 1}: BOX BOUNDS needs 3 boundary flags, got {flags}")
    periodic = [f == "pp" for f in flags] or [True] * 3
    if k + 3 >= len(lines):
        raise ValueError(f"line {k + 1}: the file ends inside BOX BOUNDS")
    try:
        b = np.array([lines[k + 1 + a].split() for a in range(3)], dtype=float)
    except ValueError:
        raise ValueError(f"line {k + 2}: BOX BOUNDS needs 3 rows of numbers") from None
    if kind == ["abc", "origin"]:  # rows: a_x a_y a_z origin_x, ...
        if b.shape != (3, 4):
            raise ValueError(f"line {k + 2}: BOX BOUNDS abc origin needs 3 rows of 4 numbers")
        return _diagonal_cell(b[:, :3], k + 1), b[:, 3].copy(), periodic
    if kind == ["xy", "xz", "yz"]:  # rows: lo hi tilt (bounding box)
        if b.shape != (3, 3):
            raise ValueError(f"line {k + 2}: BOX BOUNDS xy xz yz needs 3 rows of 3 numbers")
        if np.any(b[:, 2] != 0):
            raise ValueError(f"line {k + 1}: a triclinic box; parjam needs a cubic box")
        b = b[:, :2]
    elif kind:
        raise ValueError(f"line {k + 1}: BOX BOUNDS {' '.join(kind)}: not a box parjam reads")
    if b.ndim != 2 or b.shape[1] != 2:
        raise ValueError(f"line {k + 2}: BOX BOUNDS needs 3 rows 'lo hi'")
    return b[:, 1] - b[:, 0], b[:, 0].copy(), periodic
