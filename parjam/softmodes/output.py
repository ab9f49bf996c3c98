"""The file of ``parjam softmodes``: /softmodes/* (docs/file-format.md), written atomically on
rank 0.  Per-particle and per-contact data live on the ranks that own them and reach rank 0
one rank's block at a time (:func:`blocks_in_turn`), each written at its particle ids: rank 0
never holds all N rows, only one rank's block of one column block of the basis."""

import numpy as np

from parjam.files import h5md
from parjam.softmodes.cut import AXES
from parjam.softmodes.linalg import columns_of

TAG = 7301  # point-to-point tag of the blocks sent to rank 0


def blocks_in_turn(mpi, block, root=0):
    """On ``root``: each rank's ``block`` in rank order (its own included), received one at a
    time as the caller iterates; elsewhere the block is sent and nothing is yielded.  The
    caller must iterate to the end on ``root`` (also on error) so that every send completes."""
    if mpi.Get_rank() != root:
        mpi.send(block, dest=root, tag=TAG)
        return
    for r in range(mpi.Get_size()):
        yield block if r == root else mpi.recv(source=r, tag=TAG)


def cut_pairs(cs, root=0):
    """The q cut contacts as (i, j) particle ids, i < j, rows sorted (on ``root``; None
    elsewhere; collective).  Each cut contact is two half-edges, one on the owner of each end:
    the pair of active numbers is the key that matches them, each end gives its own id."""
    c = cs.cut
    rec = np.stack([np.minimum(c.i, c.j), np.maximum(c.i, c.j), cs.ids[c.i - cs.lo]], axis=1)
    parts = list(blocks_in_turn(cs.comm, rec, root))
    if cs.comm.Get_rank() != root:
        return None
    rec = np.concatenate(parts).reshape(-1, 3)
    rec = rec[np.lexsort((rec[:, 2], rec[:, 1], rec[:, 0]))]
    pairs = np.sort(rec[:, 2].reshape(-1, 2), axis=1)  # both ends of each key, adjacent
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))].astype(np.int64)


def localised_ids(cs, root=0):
    """Particle ids of the particles left with fewer than d contacts, ascending (on ``root``;
    collective)."""
    mine = cs.ids[cs.localised_particles - cs.lo]
    parts = list(blocks_in_turn(cs.comm, mine, root))
    return np.sort(np.concatenate(parts)).astype(np.int64) if parts else None


def write(comm, path, res, vectors=False, prov=None, block=64):
    """/softmodes/* (docs/file-format.md), written atomically on rank 0 (collective); the basis
    only with ``vectors``, each rank's rows sent to rank 0 in turn, ``block`` modes at a time."""
    mpi = comm.tompi4py()
    cut = cut_pairs(res.cs)
    loc = localised_ids(res.cs)
    if mpi.Get_rank() != 0:
        if vectors and mpi.bcast(None, root=0):  # rank 0 has the dataset open
            for start in range(0, res.n_soft, block):
                list(blocks_in_turn(mpi, basis_block(res, start, block)))
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


def basis_block(res, start, block):
    """(particle ids, modes start.. of this rank's rows as (modes, particles, d))."""
    cols = columns_of(res.V, start, min(start + block, res.n_soft))
    rows = cols.T.reshape(cols.shape[1], res.cs.n_local, res.cs.d)
    return res.cs.ids, rows


def write_basis(mpi, dset, res, block):
    """Rank 0: every rank's rows of each block of modes, received in turn and written at their
    particle ids (rattlers stay zero, the fill value).  On a failed write the remaining blocks
    are still received, then the error is raised."""
    error = None
    for start in range(0, res.n_soft, block):
        for ids, rows in blocks_in_turn(mpi, basis_block(res, start, block)):
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
