"""``parjam analyze``: the contact-network summary of packing files."""

import json

import numpy as np


def add_parser(sub):
    p = sub.add_parser("analyze", help="contact network summary of packing files",
                       description="Contacts, rattlers (fewer than d+1 contacts, removed "
                       "iteratively), N', z, dz = z - 2d, Nc - Nc_iso with Nc_iso = d(N'-1)+1, "
                       "dz_iso = z - z_iso = 2(Nc - Nc_iso)/N', "
                       "pressure, energy per particle, phi and the residual force.")
    p.add_argument("files", nargs="+", help="packing HDF5 files")
    p.add_argument("--json", action="store_true", help="one JSON object per file")
    p.set_defaults(run=run)


def run(args):
    from mpi4py import MPI

    from parjam.io import read_packing
    from parjam.network import analyze

    rank = MPI.COMM_WORLD.Get_rank()
    for path in args.files:
        net = analyze(read_packing(path))
        if rank != 0:
            continue
        s = net.summary()
        if args.json:
            print(json.dumps({"file": path, **{k: _plain(v) for k, v in s.items()}}))
            continue
        print(f"{path}")
        for key, val in s.items():
            fmt = f"{val:.12g}" if isinstance(val, float) else f"{val}"
            print(f"  {key:<20} {fmt}")
    return 0


def _plain(v):
    return v.item() if isinstance(v, np.generic) else v
