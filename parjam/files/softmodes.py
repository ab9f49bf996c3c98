"""The file of ``parjam softmodes``: /softmodes/* (docs/reference/file-format.md), written atomically on
rank 0.  Per-particle data live on the ranks that own them and reach rank 0 one rank's block at
a time (net.domain.blocks_in_turn), each written at its particle ids: rank 0 never holds all N
rows, only one rank's block of one column block of the basis.  The cut contacts and the
localised particles come gathered (parjam.softmodes.gather)."""

import numpy as np

from parjam.files import h5md
from parjam.net.domain import blocks_in_turn

AXES = "xyz"


def write(comm, path, res, cut, localised, vectors=False, prov=None, block=64):
    """/softmodes/* (docs/reference/file-format.md) of the analysis ``res`` (parjam.softmodes.SoftModes),
    written atomically on rank 0 (collective); ``cut`` and ``localised`` are the ids
    gathered on rank 0 (parjam.softmodes.gather); the basis only with ``vectors``, each rank's
    rows sent to rank 0 in turn, ``block`` modes at a time."""
    mpi = comm.tompi4py()
    loc = localised
    if mpi.Get_rank() != 0:
        if vectors and mpi.bcast(None, root=0):  # rank 0 has the dataset open
            for start in range(0, res.n_soft, block):
                list(blocks_in_turn(mpi, res.basis_block(start, block)))
        return
    opened = False
    try:
        with h5md.atomic_h5(path) as f:
            h5md.write_h5md_header(f, prov)
            g = f.create_group("softmodes")
            write_tables(g, res, cut, loc)
            if vectors:
                dset = g.create_dataset("basis", shape=(res.n_soft, res.cs.n_total, res.cs.d),
                                        dtype="f8")
                dset.attrs["layout"] = "mode, particle (packing index; rattlers zero), component"
                opened = mpi.bcast(True, root=0)
                write_basis(mpi, dset, res, block)
    finally:
        if vectors and not opened:
            mpi.bcast(False, root=0)


def write_basis(mpi, dset, res, block):
    """Rank 0: every rank's rows of each block of modes, received in turn and written at their
    particle ids (rattlers stay zero, the fill value).  On a failed write the remaining blocks
    are still received, then the error is raised."""
    error = None
    for start in range(0, res.n_soft, block):
        for ids, rows in blocks_in_turn(mpi, res.basis_block(start, block)):
            if error is not None or not len(ids):
                continue
            order = np.argsort(ids)
            try:
                dset[start:start + rows.shape[0], ids[order], :] = rows[:, order, :]
            except Exception as exc:  # keep receiving: the other ranks are sending
                error = exc
    if error is not None:
        raise error


def write_tables(g, res, cut, localised):
    cs = res.cs
    g.attrs["planes"] = np.array([p.label.encode() for p in cs.planes])
    g.attrs["planes_q"] = np.array(cs.per_plane, dtype=np.int64)
    g.create_dataset("cut_contacts", data=cut.reshape(-1, 2))
    cnt = g.create_dataset("count", data=np.int64(res.count))
    for key, val in (("trivial", cs.trivial), ("localised", cs.localised), ("q", cs.q),
                     ("expected_if_isostatic", cs.expected), ("excess", cs.excess),
                     ("N_active", cs.n), ("Nc", cs.n_contacts), ("n_basis", res.n_soft),
                     ("gap", res.gap), ("eq3_residual", res.eq3),
                     ("orthonormality", res.ortho)):
        cnt.attrs[key] = val
    cnt.attrs["localised_particles"] = localised
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
