"""The file of ``parjam softmodes``: /softmodes/* (docs/file-format.md), written atomically on
rank 0; the basis, when asked for, gathered there in blocks of columns."""

import numpy as np

from parjam import io
from parjam.softmodes.cut import AXES
from parjam.softmodes.linalg import columns_of


def gather_columns(comm, V, cols, root=0):
    """Rows of V[:, cols] from every rank, stacked on ``root`` (None elsewhere)."""
    parts = comm.tompi4py().gather(np.ascontiguousarray(columns_of(V, cols.start, cols.stop)),
                                   root=root)
    return np.concatenate(parts, axis=0) if parts is not None else None


def write(comm, path, res, vectors=False, prov=None, block=64):
    """/softmodes/* (docs/file-format.md), written atomically on rank 0; the basis only with
    ``vectors`` (gathered to rank 0 in blocks of columns)."""
    rank = comm.getRank()
    if rank != 0:
        for start in range(0, res.n_soft, block) if vectors else []:
            gather_columns(comm, res.V, slice(start, start + block))
        return
    with io.atomic_h5(path) as f:
        io.write_h5md_header(f, prov)
        g = f.create_group("softmodes")
        write_tables(g, res)
        if vectors:
            write_basis(comm, g, res, block)


def write_tables(g, res):
    cs = res.cs
    g.attrs["planes"] = np.array([p.label.encode() for p in cs.planes])
    g.attrs["planes_q"] = np.array(cs.per_plane, dtype=np.int64)
    g.create_dataset("cut_contacts", data=cs.cut_original())
    cnt = g.create_dataset("count", data=np.int64(res.count))
    for key, val in (("trivial", cs.trivial), ("localised", cs.localised), ("q", cs.q),
                     ("expected_if_isostatic", cs.expected), ("excess", cs.excess),
                     ("N_active", cs.n), ("Nc", len(cs.contacts)), ("n_basis", res.n_soft),
                     ("gap", res.gap), ("eq3_residual", res.eq3),
                     ("orthonormality", res.ortho)):
        cnt.attrs[key] = val
    cnt.attrs["localised_particles"] = cs.original[cs.localised_particles]
    ext = g.create_dataset("extension", data=res.e)
    ext.attrs["definition"] = "sum_i g_i^2 |dR_i|^2, g = product of sin(pi u/l) over cut axes"
    ov = g.create_dataset("overlap", data=res.overlap)
    ov.attrs["columns"] = ("x/L from the first plane, f (integral 1), f with the trivially "
                           "localised modes projected out (integral 1)")
    ov.attrs["axis"] = AXES[cs.planes[0].axis]
    ov.attrs["c"] = res.c_bound
    ov.attrs["c_nontrivial"] = res.c_nontrivial
    te = g.create_dataset("trial_energy", data=res.trial_energy)
    for key, val in (("e0", res.e0), ("omega_L2", res.omega_L2), ("grad_g_max2", res.grad2),
                     ("kappa", cs.kappa), ("z_max", cs.z_max), ("q_prime", res.q_prime),
                     ("omega_t2", res.omega_t2), ("n_below_2omega_t2", res.n_below),
                     ("mean_modulated_energy", float(np.mean(res.modulated_energy)))):
        te.attrs[key] = val
    fr = g.create_dataset("extended_fraction", data=res.fractions)
    fr.attrs["columns"] = "e0, q'/q"
    for key, val in res.solver.items():
        g.attrs[key] = val


def write_basis(comm, g, res, block):
    cs = res.cs
    N = cs.n_total
    dset = g.create_dataset("basis", shape=(res.n_soft, N, cs.d), dtype="f8")
    dset.attrs["layout"] = "mode, particle (packing index; rattlers zero), component"
    for start in range(0, res.n_soft, block):
        cols = slice(start, min(start + block, res.n_soft))
        rows = gather_columns(comm, res.V, cols)
        full = np.zeros((rows.shape[1], N, cs.d))
        full[:, cs.original, :] = rows.T.reshape(rows.shape[1], cs.n, cs.d)
        dset[cols] = full
