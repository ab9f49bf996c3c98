"""``parjam analyze``: the contact-network summary of packing files."""

from parjam import units
from parjam.files import outputs


def add_parser(sub):
    p = sub.add_parser("analyze", help="contact network summary of packing files",
                       description="Contacts, rattlers (fewer than d+1 contacts, removed "
                       "iteratively), N', z, dz = z - 2d, Nc - Nc_iso with Nc_iso = d(N'-1)+1, "
                       "dz_iso = z - z_iso = 2(Nc - Nc_iso)/N', "
                       "pressure, energy per particle, phi and the residual force, in reduced "
                       "units (sigma, eps, tau; the text output names each unit).")
    p.add_argument("files", nargs="+", help="packing HDF5 files")
    p.add_argument("--json", action="store_true", help="one JSON object per file")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="accepted like every command's -q: analyze prints its results only")
    p.set_defaults(run=run, reads=lambda a: a.files)


def run(args):
    from mpi4py import MPI

    from parjam.files import rowio
    from parjam.net import active

    rank = MPI.COMM_WORLD.Get_rank()
    for path in args.files:  # each rank reads its rows; the network is distributed (parjam.net.active)
        net = active.from_rows(MPI.COMM_WORLD, rowio.read_rows(MPI.COMM_WORLD, path))
        if rank != 0:
            continue
        s = defined(net.summary())
        if args.json:
            print(outputs.json_text({"file": path, **s}))
            continue
        print(f"{path}")
        for key, val in s.items():
            fmt = (UNDEFINED if val is None else f"{val:.12g}" if isinstance(val, float)
                   else f"{val}")
            unit = f" {units.text(UNIT_OF[key], net.d)}" if key in UNIT_OF and val is not None \
                else ""
            print(f"  {key:<20} {fmt}{unit}")
    return 0


#: the dimensionful entries of the summary and their quantity (parjam.units); the others are
#: dimensionless (phi, counts, z, dz, dz_iso, max_force_rel)
UNIT_OF = {"pressure": "pressure", "energy_per_particle": "energy", "max_force": "force"}


UNDEFINED = "undefined (every particle is a rattler)"
#: quantities of the rigid network, undefined when no particle is left after rattler removal
#: (Nc_iso = d (N' - 1) + 1 would be 1 - d, the excess d - 1, z = 0/0, max_force_rel = x/0)
OF_THE_NETWORK = ("Nc_iso", "excess", "z", "dz", "max_force_rel")


def defined(summary):
    """The summary with Python numbers, and None (JSON null) for what is undefined: the
    network's quantities when N' = 0, and any NaN or infinity."""
    out = outputs.plain(summary)
    if not out.get("N_active"):
        out.update({key: None for key in OF_THE_NETWORK if key in out})
    return out
