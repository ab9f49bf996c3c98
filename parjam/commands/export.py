"""``parjam export``: a packing as extended XYZ, which OVITO and ASE read."""

import os


def add_parser(sub):
    p = sub.add_parser("export", help="write a packing as extended XYZ (OVITO, ASE)")
    p.add_argument("file", help="packing HDF5 file")
    p.add_argument("--out", help="output .xyz (default: FILE with .xyz)")
    p.set_defaults(run=run)


def run(args):
    from mpi4py import MPI

    from parjam.io import read_packing, write_extxyz
    from parjam.network import analyze

    pack = read_packing(args.file)
    out = args.out or os.path.splitext(args.file)[0] + ".xyz"
    if MPI.COMM_WORLD.Get_rank() == 0:
        write_extxyz(out, pack, analyze(pack))
        print(out)
    return 0
