"""``parjam modes --out`` written by row blocks (parjam.files.rowio): the packing is never read whole
(h5md.read_packing made to fail), and the file holds what the rank-0 writer wrote: /particles/all
bit for bit as read_packing gives it, the non-rattlers' ids in particle-id order, eigenvectors
(particle-id order) that are eigenvectors of the dense matrix.  1 rank and 2 (the MPI pass:
the active rows are not in particle-id order there)."""

import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam import cli
from parjam.files import h5md
from parjam.net import network
from parjam.testing.reference import dense_system
from parjam.vib.dense import dense_matrix

from conftest import DATA

COMM = MPI.COMM_WORLD
SOFT = os.path.join(DATA, "soft_d2_N256_m0.h5")  # 15 rattlers
REF3 = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")


def with_species(shared_tmp):
    """SOFT with a /particles/all/species of 0s and 1s (written by rank 0)."""
    path = os.path.join(shared_tmp, "soft-species.h5")
    if COMM.rank == 0:
        with open(SOFT, "rb") as src, open(path, "wb") as dst:
            dst.write(src.read())
        with h5py.File(path, "a") as f:
            n = len(f["particles/all/diameter"])
            f["particles/all/species"] = np.random.default_rng(1).integers(0, 2, n)
    COMM.Barrier()
    return path


@pytest.mark.parametrize("path, method", [(SOFT, "sinvert"), ("species", "sinvert"),
                                          (REF3, "dense")])
def test_modes_file_by_rows(shared_tmp, monkeypatch, path, method):
    path = with_species(shared_tmp) if path == "species" else path
    pack = h5md.read_packing(path)  # the reference, before reading the whole file is forbidden
    net = network.analyze(pack)
    system = dense_system(pack, net)
    out = os.path.join(shared_tmp, f"rows-{method}-{os.path.basename(path)}")

    def whole(*args, **kw):
        raise AssertionError("modes read the whole packing")

    monkeypatch.setattr(h5md, "read_packing", whole)
    code = cli.main(["modes", path, "--k", "8", "--method", method, "--vectors", "--out", out,
                     "-q"])
    monkeypatch.undo()
    assert code == 0
    COMM.Barrier()
    with h5py.File(out, "r") as f:
        part = f["particles/all"]
        assert np.array_equal(part["position/value"][()], pack.pos[None])
        assert part["position/value"].dtype == np.float64
        assert np.array_equal(part["diameter"][()], pack.diam)
        assert part["diameter"].attrs["unit"] == b"sigma"
        species = pack.meta.get("species", np.zeros(pack.n))
        assert part["species"].dtype == np.int32
        assert np.array_equal(part["species"][()], np.asarray(species, np.int32))
        assert np.array_equal(part["box/edges/value"][()], np.full((1, pack.d), pack.L))
        assert list(part["position/step"][()]) == [0] and list(part["position/time"][()]) == [0]
        active = f["modes/active_particles"][()]
        assert active.dtype == np.int64 and np.array_equal(active, np.flatnonzero(~net.rattler))
        lam, vec = f["modes/eigenvalue"][()], f["modes/eigenvector"][()]
    assert vec.shape == (8, system.n, pack.d)
    H = dense_matrix(system, "full")
    norm = np.abs(H).sum(axis=1).max()
    for k in range(8):  # rows in particle-id order: an eigenvector of D in the serial numbering
        v = vec[k].ravel()
        assert np.linalg.norm(H @ v - lam[k] * v) <= 1e-8 * norm * np.linalg.norm(v)
