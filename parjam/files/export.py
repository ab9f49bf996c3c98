"""A parjam packing in the files other programs open (``parjam export``, docs/howto/clients.md):

- **extended XYZ** in the standard column order (``species:S:1:pos:R:3`` first: chemfiles and
  LAMMPS read the first columns as name and position), then ``Z``, ``radius``, ``type`` and
  ``rattler``; the cell in ``Lattice``; read by ASE, OVITO, chemfiles, MDAnalysis and LAMMPS;
- **LAMMPS data** (``units lj``), atom_style ``sphere`` (id type diameter density x y z, the
  density giving every particle parjam's unit mass) or ``atomic`` (id type x y z and a
  ``Masses`` section), types counted from 1;
- **GSD** (HOOMD-blue's format, through the ``gsd`` package): the HOOMD schema's
  single-precision positions in a box centred on the origin, ``typeid``, ``types``,
  ``diameter`` and ``mass``; a 2D packing has ``dimensions = 2`` and Lz = 0.  Exact float64
  copies of the positions and diameters ride along in ``log/parjam/*``, so that ``parjam
  import`` gets the packing back bit for bit (and falls back to the single-precision arrays
  when another program rewrote them).

Species: the distinct values of the packing's species, in increasing order, become types 1, 2,
... (LAMMPS, OVITO, the ``type`` column) and names A, B, ... (``species``, GSD ``types``, the
comments of a LAMMPS ``Masses`` section).  ASE builds Atoms from chemical elements only, so the XYZ also has ``Z`` = the
type: ASE shows the species as H, He, ... and keeps ``arrays["type"]``.

Every writer takes the packing and its rattler flags (computed by the caller: this module
computes no physics) and writes atomically (parjam.files.outputs).
"""

import os

import numpy as np

from parjam import __version__
from parjam.errors import ParjamError
from parjam.files import outputs
from parjam.files.formats import EXPORT_ATOM_STYLES, EXPORT_EXTENSIONS, EXPORT_FORMATS
from parjam.net.system import sphere_volume

FORMATS, EXTENSIONS = EXPORT_FORMATS, EXPORT_EXTENSIONS
ATOM_STYLES = EXPORT_ATOM_STYLES
MAX_TYPES = 26 * 27  # names A .. Z, then AA .. ZZ: more distinct species than any dispersity


def detect_format(path, fmt=None):
    """``fmt`` when given, else the format of ``path``'s extension; ParjamError otherwise."""
    if fmt is not None:
        if fmt not in FORMATS:
            raise ParjamError(f"unknown export format {fmt!r}; choose from {', '.join(FORMATS)}")
        return fmt
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in EXTENSIONS:
        return EXTENSIONS[ext]
    raise ParjamError(f"{path}: cannot tell the export format from the extension "
                      f"{ext or '(none)'}; give --format ({', '.join(FORMATS)}) or end the name "
                      f"in {', '.join(EXTENSIONS)}")


def type_name(k):
    """The name of 0-based type ``k``: A .. Z, then AA, AB, ..."""
    letters = "ABCDEFGHIJKLMNOPQRSTUVWXYZ"
    return letters[k] if k < 26 else letters[k // 26 - 1] + letters[k % 26]


def types_of(pack):
    """(0-based type of every particle, type names): the packing's distinct species in
    increasing order (one type when the file names none)."""
    species = pack.meta.get("species")
    species = np.zeros(pack.n, np.int64) if species is None else np.asarray(species, np.int64)
    kinds, typeid = np.unique(species, return_inverse=True)
    if len(kinds) > MAX_TYPES:
        raise ParjamError(f"{len(kinds)} species: more than the {MAX_TYPES} types an export "
                          f"names")
    return typeid.astype(np.int64), [type_name(k) for k in range(len(kinds))]


def _check(pack, rattler):
    rattler = np.asarray(rattler, bool)
    if rattler.shape != (pack.n,):
        raise ParjamError(f"{len(rattler)} rattler flags for {pack.n} particles")
    return rattler


def _comment(pack):
    return (f"parjam {__version__}: N = {pack.n}, d = {pack.d}, phi = {pack.phi:.17g}, "
            f"alpha = {pack.alpha:.17g}, epsilon = {pack.eps:.17g}; reduced units (sigma = "
            f"smallest diameter, epsilon, unit masses)")


# --- extended XYZ -------------------------------------------------------------------------------

def extxyz_text(pack, rattler):
    """The extended XYZ of one packing (module doc).  In 2D the third cell vector is as long
    as the largest diameter (3D viewers need a non-zero cell) and pbc is "T T F"."""
    rattler = _check(pack, rattler)
    typeid, names = types_of(pack)
    d = pack.d
    third = pack.L if d == 3 else float(pack.diam.max())
    lattice = f"{pack.L:.17g} 0 0 0 {pack.L:.17g} 0 0 0 {third:.17g}"
    head = (f'Lattice="{lattice}" Properties=species:S:1:pos:R:3:Z:I:1:radius:R:1:type:I:1:'
            f'rattler:I:1 pbc="T T {"T" if d == 3 else "F"}" dimension={d} '
            f"phi={pack.phi:.17g} alpha={pack.alpha:.17g} epsilon={pack.eps:.17g} "
            f'units="sigma epsilon tau" types="{" ".join(names)}"')
    pos = np.zeros((pack.n, 3))
    pos[:, :d] = pack.pos
    lines = [str(pack.n), head]
    for k in range(pack.n):
        t = int(typeid[k])
        x, y, z = pos[k]
        lines.append(f"{names[t]} {x:.17g} {y:.17g} {z:.17g} {t + 1} "
                     f"{pack.diam[k] / 2:.17g} {t + 1} {int(rattler[k])}")
    return "\n".join(lines) + "\n"


def write_extxyz(path, pack, rattler):
    outputs.write_bytes(path, extxyz_text(pack, rattler).encode())


# --- LAMMPS data --------------------------------------------------------------------------------

def lammps_data_text(pack, rattler, style="sphere"):
    """A LAMMPS data file (module doc) for ``units lj``, ``atom_style STYLE`` and, in 2D,
    ``dimension 2`` (z = 0 inside zlo = -0.5, zhi = 0.5).  The type names are in the first
    line and, for atomic, as comments of the Masses lines (OVITO reads them there); an ``Atom
    Type Labels`` section is left out because chemfiles 0.10 loops forever on it.  Rattlers
    are counted in the first line only (a data file has no free per-atom column)."""
    if style not in ATOM_STYLES:
        raise ParjamError(f"unknown atom style {style!r}; choose from {', '.join(ATOM_STYLES)}")
    rattler = _check(pack, rattler)
    typeid, names = types_of(pack)
    d = pack.d
    out = [f"LAMMPS data file (atom_style {style}, units lj{', dimension 2' if d == 2 else ''}) "
           f"from {_comment(pack)}; types {' '.join(f'{k + 1} = {n}' for k, n in enumerate(names))}"
           f"; {int(rattler.sum())} rattlers", "",
           f"{pack.n} atoms", f"{len(names)} atom types", "",
           f"0 {pack.L:.17g} xlo xhi", f"0 {pack.L:.17g} ylo yhi",
           f"0 {pack.L:.17g} zlo zhi" if d == 3 else "-0.5 0.5 zlo zhi", ""]
    if style == "atomic":
        out += ["Masses", ""] + [f"{k + 1} 1 # {name}" for k, name in enumerate(names)] + [""]
    out += [f"Atoms # {style}", ""]
    # sphere: read_data sets the mass to density x 4/3 pi r^3, in 2D too: unit masses
    density = 1.0 / sphere_volume(pack.diam, 3)
    pos = np.zeros((pack.n, 3))
    pos[:, :d] = pack.pos
    for k in range(pack.n):
        x, y, z = pos[k]
        extra = f" {pack.diam[k]:.17g} {density[k]:.17g}" if style == "sphere" else ""
        out.append(f"{k + 1} {int(typeid[k]) + 1}{extra} {x:.17g} {y:.17g} {z:.17g} 0 0 0")
    return "\n".join(out) + "\n"


def write_lammps_data(path, pack, rattler, style="sphere"):
    outputs.write_bytes(path, lammps_data_text(pack, rattler, style).encode())


# --- GSD ----------------------------------------------------------------------------------------

def gsd_module():
    try:
        import gsd.hoomd
    except ImportError:
        raise ParjamError("GSD files need the gsd package (pip install gsd)") from None
    return gsd.hoomd


def centred_single(pos, L):
    """Positions in [0, L) as HOOMD's single-precision positions in [-L/2, L/2): rounding to
    float32 may land a coordinate on +L/2, which is folded to -L/2."""
    half = np.float32(L / 2.0)
    x = (np.asarray(pos, float) - L / 2.0).astype(np.float32)
    x[x >= half] -= np.float32(L)
    x[x < -half] = -half
    return x


def gsd_frame(pack, rattler):
    """One gsd.hoomd.Frame of the packing (module doc)."""
    hoomd = gsd_module()
    rattler = _check(pack, rattler)
    typeid, names = types_of(pack)
    d = pack.d
    frame = hoomd.Frame()
    frame.configuration.step = 0
    frame.configuration.dimensions = d
    frame.configuration.box = [pack.L, pack.L, pack.L if d == 3 else 0.0, 0.0, 0.0, 0.0]
    full = np.zeros((pack.n, 3))
    full[:, :d] = pack.pos
    single = centred_single(full, pack.L)
    if d == 2:
        single[:, 2] = 0.0  # the plane z = 0 (Lz = 0)
    frame.particles.N = pack.n
    frame.particles.types = names
    frame.particles.typeid = typeid.astype(np.uint32)
    frame.particles.position = single
    frame.particles.diameter = pack.diam.astype(np.float32)
    frame.particles.mass = np.ones(pack.n, np.float32)
    frame.log = {"parjam/position": full, "parjam/diameter": pack.diam.copy(),
                 "parjam/box_edge": np.array([pack.L]), "parjam/alpha": np.array([pack.alpha]),
                 "parjam/epsilon": np.array([pack.eps]), "parjam/phi": np.array([pack.phi]),
                 "parjam/rattler": rattler.astype(np.uint8)}
    return frame


def write_gsd(path, pack, rattler):
    hoomd = gsd_module()
    frame = gsd_frame(pack, rattler)
    with outputs.atomic_path(path) as tmp:
        with hoomd.open(tmp, "w") as traj:
            traj.append(frame)


def export(path, pack, rattler, fmt=None, atom_style="sphere"):
    """Write ``pack`` to ``path`` in ``fmt`` (default: from the extension)."""
    fmt = detect_format(path, fmt)
    if fmt == "extxyz":
        write_extxyz(path, pack, rattler)
    elif fmt == "lammps-data":
        write_lammps_data(path, pack, rattler, atom_style)
    else:
        write_gsd(path, pack, rattler)
    return fmt
