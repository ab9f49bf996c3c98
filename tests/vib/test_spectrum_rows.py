"""Eigenvectors of a distributed system stay with their rows (parjam.vib.spectrum on the active
network): each rank holds (K, its active rows, d), tagged with its particle ids, never all N';
put together by id they are the 1-rank vectors up to sign, and eigenvectors of the dense
matrix.  1 rank and 2 (the MPI pass)."""

import os

import numpy as np
from mpi4py import MPI

from parjam.testing.reference import dense_system
from parjam.vib.dense import dense_matrix
from parjam import env
from parjam.files import rowio
from parjam.net import active, network
from parjam.vib import spectrum
from parjam.files.h5md import read_packing

from conftest import DATA

COMM = MPI.COMM_WORLD
WORLD = env.petsc().COMM_WORLD
SOFT = os.path.join(DATA, "soft_d2_N256_m0.h5")


def test_vectors_stay_on_their_rows():
    system = spectrum.distributed_system(active.from_rows(WORLD, rowio.read_rows(WORLD, SOFT)))
    spec = spectrum.compute(WORLD, system, "full", k=6, method="sinvert", vectors=True)
    assert np.array_equal(spec.vector_ids, system.ids)
    assert spec.vectors.shape == (len(spec.eigenvalue), len(system.ids), system.d)
    assert COMM.allreduce(len(system.ids)) == system.n  # the rows add up to N', once each
    # put together in particle-id order: eigenvectors of the dense matrix of the same packing
    ids = np.concatenate(COMM.allgather(spec.vector_ids))
    vec = np.concatenate(COMM.allgather(spec.vectors.transpose(1, 0, 2)))[np.argsort(ids)]
    pack = read_packing(SOFT)
    H = dense_matrix(dense_system(pack, network.analyze(pack)), "full")
    V = vec.transpose(1, 0, 2).reshape(len(spec.eigenvalue), -1).T
    res = np.linalg.norm(H @ V - V * spec.eigenvalue, axis=0) / np.abs(H).sum(axis=1).max()
    assert res.max() < 1e-9
