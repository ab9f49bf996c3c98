"""The file of ``parjam moduli --out``: /moduli/* (tensors, scalars, the solver's report) of a
parjam.vib.moduli.Moduli result, HDF5 written atomically by one rank."""

import numpy as np

from parjam.files import h5md


def write(path, mod, prov=None):
    """Write /moduli/* (tensors, scalars, solver report) atomically; call on one rank."""
    with h5md.atomic_h5(path) as f:
        h5md.write_h5md_header(f, prov)
        g = f.create_group("moduli")
        for key, val in mod.summary().items():
            if val is None or isinstance(val, list):
                continue
            g.attrs[key] = val
        for name in ("stress", "c_affine", "c_energy", "c_lagrangian", "stiffness"):
            g.create_dataset(name, data=getattr(mod, name))
        s = g.create_group("solver")
        s.create_dataset("residuals", data=np.array(mod.solver["residuals"]))
        s.create_dataset("iterations", data=np.array(mod.solver["iterations"]))
        for key in ("tau", "ksp_type", "pc_type", "rtol", "max_residual"):
            s.attrs[key] = mod.solver[key]
