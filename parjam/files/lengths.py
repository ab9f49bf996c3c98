"""The file of ``parjam lengths --out``: the /lengths group (HDF5, written by one rank) of a
parjam.lengths.Lengths result."""

import numpy as np

from parjam.files import h5md

CUBE_COLUMNS = ("ell", "n", "q", "nc_in", "n_core", "nc_core", "trivial", "pieces", "null",
                "soft", "maxwell", "maxwell_core", "extended")


def write(path, res, prov=None):
    """/lengths/* atomically (call on one rank)."""
    with h5md.atomic_h5(path) as f:
        h5md.write_h5md_header(f, prov)
        g = f.create_group("lengths")
        g.attrs["density_convention"] = "rho = N' / V: non-rattlers, unit masses"
        for key, val in res.summary().items():
            g.attrs[key] = val
        if res.moduli is not None:
            s = g.create_group("moduli")
            s.create_dataset("stiffness", data=res.moduli.stiffness)
            s.create_dataset("stress", data=res.moduli.stress)
            s.attrs["max_residual"] = res.moduli.solver["max_residual"]
        if res.spectrum is not None:
            s = g.create_group("spectrum")
            s.create_dataset("frequency", data=res.spectrum.frequency)
            s.attrs["matrix"] = res.spectrum.matrix
            s.attrs["method"] = res.spectrum.method
            s.attrs["plateau_window"] = np.asarray(res.dos[2], float)
            s.attrs["n_negative"] = res.spectrum.n_negative
        if res.lstar is not None:
            write_lstar(g.create_group("lstar"), res.lstar)
        if res.structure is not None:
            write_structure(g.create_group("structure"), res.structure, res.structure_fit)


def write_lstar(g, ls):
    """The cube table, every cube's counts and the fitted lengths into group ``g``."""
    g.create_dataset("edges", data=ls.ells)
    g.create_dataset("table", data=ls.table())
    g["table"].attrs["columns"] = ", ".join(ls.COLUMNS)
    g.create_dataset("cubes", data=np.array(
        [[getattr(c, a) for a in CUBE_COLUMNS] for c in ls.counts],
        dtype=float).reshape(-1, len(CUBE_COLUMNS)))
    g["cubes"].attrs["columns"] = ", ".join(CUBE_COLUMNS)
    for key in ("estimate", "measured", "soft_measured", "extended_measured", "samples",
                "failed", "dz", "z", "e0"):
        g.attrs[key] = getattr(ls, key)


def write_structure(g, sf, fit):
    """Shell weights, peaks and the dispersion fit into group ``g``."""
    for name in ("omega", "k", "m2", "n_vectors", "weight_L", "weight_T"):
        g.create_dataset(name, data=getattr(sf, name))
    g.create_dataset("peak_L", data=fit["peak_L"])
    g.create_dataset("peak_T", data=fit["peak_T"])
    for key, val in fit.items():
        if key not in ("peak_L", "peak_T"):
            g.attrs[key] = val
