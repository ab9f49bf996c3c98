"""``parjam export``: a packing as extended XYZ, which OVITO and ASE read."""

import os

def add_parser(sub):
    p = sub.add_parser("export", help="write a packing as extended XYZ (OVITO, ASE)")
    p.add_argument("file", help="packing HDF5 file")
    p.add_argument("--out", help="output .xyz (default: FILE with .xyz)")
    p.add_argument("-q", "--quiet", action="store_true", help="do not print the name of the file written")
    p.set_defaults(run=run, reads=lambda a: [a.file])


def run(args):
    from mpi4py import MPI

    from parjam.files import outputs
    from parjam.files.h5md import read_packing, write_extxyz
    from parjam.net.network import analyze

    out = args.out or os.path.splitext(args.file)[0] + ".xyz"
    outputs.check(MPI.COMM_WORLD, files=[("--out", out)], inputs=[args.file])
    pack = read_packing(args.file)

    def write():
        with outputs.atomic_path(out) as tmp:
            write_extxyz(tmp, pack, analyze(pack))
        if not args.quiet:
            print(out)

    outputs.on_root(MPI.COMM_WORLD, write)
    return 0
