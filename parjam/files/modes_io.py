"""The spectrum file (docs/howto/spectra.md): one HDF5 file per (packing, matrix, method), H5MD header
plus

    /modes/eigenvalue            (K,)  ascending lambda = omega^2
    /modes/frequency             (K,)  sign(lambda) sqrt|lambda|
    /modes/error                 (K,)  ||D v - lambda v||_2 / ||D||_inf per pair
    /modes/participation_ratio   (K,)
    /modes/eps_perp, /modes/eps_par   (K,)  transverse / longitudinal sums (Fig. "trans")
    /modes/eigenvector           (K, N', d)  only with --vectors
    /modes/active_particles      (N',)  packing indices of the non-rattlers (rows of the matrix)
    /modes/rejected/{eigenvalue,error}  pairs above the tolerance (reported, not kept above)
    /dos/omega, /dos/edges, /dos/density  D(omega) per mode (attrs: binning, normalisation, D0,
                                          omega_star, plateau window)

with the run's settings as attributes of /modes, and the packing the modes belong to as
/particles/all (box, positions, diameters, species, as parjam.files.h5md.write_particles writes them),
so that H5MD readers such as MDAnalysis open a spectrum file like a packing file.  Written
atomically by all ranks together (parjam.files.rowio): no rank holds the packing's N rows.
"""

import json
import os

import h5py
import numpy as np

from parjam.files import h5md, inputs, rowio
from parjam.net.active import home_rows
from parjam.net.domain import as_mpi
from parjam.errors import ParjamError

FORMAT = "parjam-spectrum 1"


def mode_attrs(spec, system, packing_path, ranks):
    """Attributes of /modes: what was computed, how, and from which file."""
    return {
        "format": FORMAT, "matrix": spec.matrix, "method": spec.method,
        "tolerance": spec.tolerance, "norm_inf": spec.norm, "zero_tol": spec.zero_tol,
        "target": spec.target, "interval_lambda": np.array(spec.interval, dtype=float),
        "n_requested": spec.n_requested, "n_accepted": len(spec.eigenvalue),
        "n_rejected": len(spec.rejected_eigenvalue), "complete": bool(spec.complete),
        "n_negative": spec.n_negative, "unstable": bool(spec.unstable),
        "n_zero_modes": spec.n_zero, "n_translations": system.d,
        "translations_deflated": True, "rattlers_removed": True, "n_active": system.n,
        "n_rattlers": system.n_rattlers, "dimension": system.d, "n_contacts": system.n_contacts,
        "n_modes_total": system.n_modes, "alpha": system.alpha, "pressure": system.pressure,
        "max_force": system.max_force, "ranks": int(ranks), "seconds": spec.seconds,
        "packing_file": os.path.abspath(packing_path) if packing_path else "",
        "packing_sha256": h5md.sha256(packing_path) if packing_path else "",
        "solver_info": json.dumps(spec.info, default=float),
        **packing_state(packing_path),
    }


def packing_state(path):
    """What figures name a spectrum by: the packing's state label (``dphi1.0e-04``, ``phi_c``,
    ``p1.0e-03``, ``imported``), N and phi, from its /parameters (empty if unreadable)."""
    if not path:
        return {}
    try:
        with h5py.File(path, "r") as f:
            par = f["parameters"].attrs if "parameters" in f else {}
            state = par.get("state", "")
            out = {"state": state.decode() if isinstance(state, bytes) else str(state)}
            if "phi" in par:
                out["phi"] = float(np.asarray(par["phi"]).reshape(-1)[0])
            if "particles/all/diameter" in f:
                out["n"] = int(f["particles/all/diameter"].shape[0])
            return out
    except (OSError, KeyError, ValueError, TypeError):
        return {}


def write_spectrum(comm, path, spec, system, rows, dos, prov):
    """Write one spectrum file (collective): the per-mode arrays and attributes by rank 0, the
    per-particle datasets by row blocks (parjam.files.rowio), so that no rank holds the packing's N
    rows: /particles/all from each rank's file rows ``rows`` (rowio.read_rows), the
    non-rattlers' ids from the distributed ``system`` moved to their home rows.  The
    eigenvectors, when asked for: each rank's rows (``spec.vector_ids``) go to their home rows
    with the ids."""
    mpi = as_mpi(comm)
    want = spec.vector_ids is not None  # the same on every rank (spectrum.compute)
    k = len(spec.eigenvalue)
    if want:  # each rank's rows (K, n_r, d) travel with their ids, K d numbers a row
        ids, vec = home_rows(mpi, rows.n, spec.vector_ids,
                             spec.vectors.transpose(1, 0, 2).reshape(len(spec.vector_ids),
                                                                     k * system.d))
        vectors = vec.reshape(len(ids), k, system.d).transpose(1, 0, 2)
    else:
        ids, _ = home_rows(mpi, rows.n, system.ids)
    nbytes = spectrum_bytes(rows, system, len(spec.eigenvalue) if want else 0)
    with rowio.rows_file(mpi, path, nbytes) as out:
        out.meta(write_modes, lambda: (spec, mode_attrs(spec, system, rows.path, prov.get(
            "ranks", 1)), dos, prov, rows.d, rows.L))
        rowio.write_particle_rows(out, rows)
        out.rows("modes/active_particles", ids)
        if want:
            out.rows("modes/eigenvector", vectors, axis=1)


def spectrum_bytes(rows, system, n_vectors):
    """The size of a spectrum file's per-particle data (the reservation of rowio.rows_file)."""
    return rows.n * (8 * rows.d + 8 + 4) + 8 * system.n * (1 + n_vectors * system.d)


def write_modes(f, spec, attrs, dos, prov, d, L):
    """Everything but the per-particle rows: header, the box, /modes per-mode arrays and
    attributes, /dos."""
    h5md.write_h5md_header(f, prov)
    h5md.particles_header(f, d, L)
    g = f.create_group("modes")
    for key, val in attrs.items():
        g.attrs[key] = val
    # omega in units of 1/tau, tau = sigma sqrt(m / epsilon) with unit masses m = 1
    g.create_dataset("eigenvalue", data=spec.eigenvalue).attrs["unit"] = h5md.fixed_string("tau-2")
    g.create_dataset("frequency", data=spec.frequency).attrs["unit"] = h5md.fixed_string("tau-1")
    g.create_dataset("error", data=spec.error)
    g.create_dataset("participation_ratio", data=spec.participation_ratio)
    g.create_dataset("eps_perp", data=spec.eps_perp)
    g.create_dataset("eps_par", data=spec.eps_par)
    rej = g.create_group("rejected")
    rej.create_dataset("eigenvalue", data=spec.rejected_eigenvalue).attrs["unit"] = \
        h5md.fixed_string("tau-2")
    rej.create_dataset("error", data=spec.rejected_error)
    write_dos(f, dos)


#: /dos datasets and their units: omega in 1/tau, D(omega) per unit omega in tau
DOS_UNITS = {"omega": "tau-1", "edges": "tau-1", "density": "tau", "density_error": "tau"}


def write_dos(f, dos):
    g = f.create_group("dos")
    for key in ("omega", "edges", "density", "density_error"):
        if key in dos:
            g.create_dataset(key, data=dos[key]).attrs["unit"] = h5md.fixed_string(
                DOS_UNITS[key])
    for key, val in dos.items():
        if key not in ("omega", "edges", "density", "density_error"):
            g.attrs[key] = val


def read_spectrum(path):
    """A spectrum file as a dict of arrays and attributes; ParjamError if it is not one."""
    path = os.fspath(path)
    inputs.require(path)  # a FIFO, a directory, a loop: named, and never opened
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            if "modes" not in f or f["modes"].attrs.get("format") != FORMAT:
                raise ParjamError(f"{path}: not a parjam spectrum file (no /modes of {FORMAT!r})")
            g = f["modes"]
            out = {key: g[key][()] for key in g if isinstance(g[key], h5py.Dataset)}
            out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v)
                            for k, v in g.attrs.items()}
            out["dos"] = {key: f["dos"][key][()] for key in f["dos"]} if "dos" in f else {}
    except (OSError, RuntimeError, KeyError) as exc:  # truncated or corrupted inside
        raise ParjamError(f"{path}: unreadable HDF5 file ({exc})") from None
    return out
