"""``parjam export``: a packing as extended XYZ, which OVITO and ASE read."""

import os

from parjam.errors import ParjamError


def add_parser(sub):
    p = sub.add_parser("export", help="write a packing as extended XYZ (OVITO, ASE)")
    p.add_argument("file", help="packing HDF5 file")
    p.add_argument("--out", help="output .xyz (default: FILE with .xyz)")
    p.set_defaults(run=run)


def run(args):
    from mpi4py import MPI

    from parjam.io import read_packing, write_extxyz
    from parjam.network import analyze

    out = args.out or os.path.splitext(args.file)[0] + ".xyz"
    if os.path.isdir(out):
        raise ParjamError(f"--out {out} is a directory")
    pack = read_packing(args.file)
    if MPI.COMM_WORLD.Get_rank() == 0:
        try:
            write_extxyz(out, pack, analyze(pack))
        except OSError as exc:
            raise ParjamError(f"{out}: cannot write ({exc.strerror})", collective=False) from None
        print(out)
    return 0
