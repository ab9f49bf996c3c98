"""``parjam import``: a configuration made elsewhere (extended XYZ, LAMMPS data or dump, GSD,
another program's H5MD) as a parjam packing file, which ``parjam pack --from`` minimises, brings to phi_c
and compresses along a dphi ladder (parjam.files.importer)."""

import os
import sys

from parjam.errors import ParjamError


def add_parser(sub):
    from parjam.files.formats import IMPORT_FORMATS as FORMATS
    from parjam.files.lammpsio import STYLES as ATOM_STYLES

    p = sub.add_parser(
        "import", help="bring in a packing made elsewhere (extended XYZ, LAMMPS, GSD, H5MD)",
        description="Read the last frame of FILE (extended XYZ of ASE/OVITO, LAMMPS data "
        "(atom_style atomic, charge, molecular, full or sphere) or text dump, GSD of "
        "HOOMD-blue, or H5MD of another program) in a periodic cubic/square box, rescale "
        "lengths so that the smallest diameter is 1, and write a parjam packing file with its "
        "contact network. A volume fraction that `parjam pack` cannot start from (phi >= 1 in "
        "3D, >= 1.5 in 2D, or < 0.05) is refused. `parjam pack --from OUT` then minimises it, "
        "finds phi_c and runs the dphi ladder.")
    p.add_argument("file", help="the configuration to import")
    p.add_argument("--out", help="output packing (default: FILE's name with .parjam.h5)")
    p.add_argument("--format", choices=FORMATS,
                   help="default: from the extension (.xyz/.extxyz, .data/.lmp, "
                   ".dump/.lammpstrj, .gsd, .h5/.h5md)")
    p.add_argument("--atom-style", choices=ATOM_STYLES,
                   help="LAMMPS data: the Atoms section's layout when its header names none "
                   "and the columns fit two (7 columns: sphere or full)")
    p.add_argument("--diameters", type=float, nargs="+", metavar="D",
                   help="diameters of the species (LAMMPS types) in increasing order, for files "
                   "that give none (default: 1 when there is one species)")
    p.add_argument("--dim", type=int, choices=(2, 3),
                   help="dimension (default: from the file; LAMMPS: 2 when every z is equal)")
    p.add_argument("--alpha", type=float, default=2.0,
                   help="potential exponent when the file names none (default: 2)")
    p.add_argument("-q", "--quiet", action="store_true", help="do not print the summary line")
    p.set_defaults(run=run, reads=lambda a: [a.file])


def output_path(args):
    if args.out:
        return args.out
    return os.path.splitext(args.file)[0] + ".parjam.h5"


def run(args):
    from mpi4py import MPI

    from parjam.files import h5md, importer, outputs
    from parjam.net.network import analyze

    out = output_path(args)
    outputs.check(MPI.COMM_WORLD, files=[("--out", out)], inputs=[args.file])
    for dval in args.diameters or []:
        if not dval > 0:
            raise ParjamError(f"--diameters must be positive, got {dval}")
    pack = importer.load(args.file, args.format, args.diameters, args.dim, args.alpha,
                         args.atom_style)
    net = analyze(pack)
    meta = pack.meta
    params = {"protocol": "imported", "ladder": "none", "state": "imported",
              "dimension": pack.d, "n": pack.n, "source": meta["source"],
              "source_format": meta["source_format"], "length_scale": meta["length_scale"]}

    def write():
        h5md.write_packing(out, pack, net, params, h5md.provenance(MPI.COMM_WORLD.Get_size()))

    outputs.on_root(MPI.COMM_WORLD, write)
    if MPI.COMM_WORLD.Get_rank() == 0:
        if not args.quiet:
            print(f"{out}: N = {pack.n}, d = {pack.d}, phi = {pack.phi:.6f}, "
                  f"{len(set(meta['species'].tolist()))} species, lengths x "
                  f"{meta['length_scale']:.6g}, N' = {net.n_active}, z = {net.z:.4f}, "
                  f"max|F| = {net.max_force:.2e}", flush=True)
        if net.max_force > 1e-8:
            print(f"parjam: note: not in force balance (max|F| = {net.max_force:.1e}): "
                  f"`parjam pack --from {out}` minimises it", file=sys.stderr, flush=True)
    return 0
