"""``parjam export``: a packing as extended XYZ, LAMMPS data or GSD (parjam.files.export), the
files ASE, OVITO, MDAnalysis, freud, chemfiles, LAMMPS and HOOMD-blue open
(docs/howto/clients.md)."""

import os

from parjam.errors import ParjamError


def add_parser(sub):
    from parjam.files.formats import EXPORT_ATOM_STYLES as ATOM_STYLES
    from parjam.files.formats import EXPORT_EXTENSIONS as EXTENSIONS
    from parjam.files.formats import EXPORT_FORMATS as FORMATS

    p = sub.add_parser(
        "export", help="write a packing as extended XYZ, LAMMPS data or GSD",
        description="Write the packing FILE for other programs: extended XYZ (species, "
        "position, Z, radius, type, rattler; ASE, OVITO, chemfiles, MDAnalysis), LAMMPS data "
        "(atom_style sphere or atomic, units lj, types from 1; LAMMPS read_data, OVITO, ASE, "
        "MDAnalysis) or GSD (HOOMD-blue's format; OVITO, MDAnalysis, freud). The format comes "
        "from --out's extension (" + ", ".join(f"{e}: {f}" for e, f in EXTENSIONS.items())
        + ") unless --format is given. docs/howto/clients.md gives each program's call.")
    p.add_argument("file", help="packing HDF5 file")
    p.add_argument("--out", help="output file (default: FILE with the format's extension, "
                   ".xyz when no --format is given)")
    p.add_argument("--format", choices=FORMATS, help="default: from --out's extension")
    p.add_argument("--atom-style", choices=ATOM_STYLES, default="sphere",
                   help="lammps-data: sphere (id type diameter density x y z; default) or "
                   "atomic (id type x y z, no diameters)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="do not print the name of the file written")
    p.set_defaults(run=run, reads=lambda a: [a.file])


DEFAULT_EXTENSION = {"extxyz": ".xyz", "lammps-data": ".data", "gsd": ".gsd"}


def output_path(args):
    """--out, or FILE with the extension of --format (.xyz by default); the format."""
    from parjam.files.export import detect_format

    out = args.out or os.path.splitext(args.file)[0] + DEFAULT_EXTENSION[args.format or "extxyz"]
    return out, detect_format(out, args.format)


def run(args):
    from mpi4py import MPI

    from parjam.files import export, outputs
    from parjam.files.h5md import read_packing
    from parjam.net.network import analyze

    out, fmt = output_path(args)
    if args.atom_style != "sphere" and fmt != "lammps-data":
        raise ParjamError(f"--atom-style is for lammps-data; {out} is {fmt}")
    if fmt == "gsd":
        export.gsd_module()  # the gsd package, before any work
    outputs.check(MPI.COMM_WORLD, files=[("--out", out)], inputs=[args.file])
    pack = read_packing(args.file)

    def write():
        export.export(out, pack, analyze(pack).rattler, fmt, args.atom_style)
        if not getattr(args, "quiet", False):
            print(out, flush=True)

    outputs.on_root(MPI.COMM_WORLD, write)
    return 0
