"""Packing files read by row ranges (parjam.files.rowio): each rank's rows are the file's rows, the
distributed network equals the serial one, and bad files give read_packing's one-line error on
every rank, also when only one rank's rows hold the problem.  1 rank and 2 (the MPI pass)."""

import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam.files import rowio
from parjam.net import active
from parjam.errors import ParjamError
from parjam.files.h5md import read_packing
from parjam.net.network import analyze

from conftest import DATA

COMM = MPI.COMM_WORLD
REF = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")
SOFT = os.path.join(DATA, "soft_d2_N256_m0.h5")


@pytest.mark.parametrize("path", [REF, SOFT])
def test_rows_are_the_files_rows(path):
    pack = read_packing(path)
    rows = rowio.read_rows(COMM, path)
    assert (rows.n, rows.d, rows.L, rows.alpha) == (pack.n, pack.d, pack.L, pack.alpha)
    blocks = COMM.allgather((rows.start, rows.stop))
    assert blocks[0][0] == 0 and blocks[-1][1] == pack.n
    assert np.array_equal(rows.pos, pack.pos[rows.start:rows.stop])
    assert np.array_equal(rows.diam, pack.diam[rows.start:rows.stop])
    assert rows.stop - rows.start <= pack.n // COMM.size + 1  # no rank holds all N (P > 1)
    net = active.from_rows(COMM, rowio.read_rows(COMM, path))
    assert net.summary() == pytest.approx(analyze(pack).summary(), rel=1e-12, abs=1e-16)


def broken(shared_tmp, name, mutate):
    """A copy of REF changed by ``mutate`` (written by rank 0)."""
    path = os.path.join(shared_tmp, name + ".h5")
    if COMM.rank == 0:
        with open(REF, "rb") as src, open(path, "wb") as dst:
            dst.write(src.read())
        with h5py.File(path, "a") as f:
            mutate(f)
    COMM.Barrier()
    return path


def set_row(key, row, value):
    def mutate(f):
        data = f[key][()]
        if data.ndim == 3:
            data[-1, row] = value
        else:
            data[row] = value
        del f[key]
        f[key] = data
    return mutate


BAD = {  # the last row: on the last rank only when P > 1
    "nan": (set_row("particles/all/position/value", -1, np.nan), "contain NaN or inf"),
    "negative": (set_row("particles/all/diameter", -1, -1.0), "must be positive"),
    "coincide": (set_row("particles/all/position/value", -1, None), "coincide"),
    "missing": (lambda f: f.__delitem__("particles/all/diameter"), "missing dataset"),
}


@pytest.mark.parametrize("name", sorted(BAD))
def test_bad_rows_fail_on_every_rank_as_read_packing(shared_tmp, name):
    mutate, message = BAD[name]
    if name == "coincide":  # the last particle on top of the first
        def mutate(f):
            data = f["particles/all/position/value"][()]
            data[-1, -1] = data[-1, 0]
            del f["particles/all/position/value"]
            f["particles/all/position/value"] = data
    path = broken(shared_tmp, name, mutate)
    with pytest.raises(ParjamError, match=message) as serial:
        read_packing(path)
    with pytest.raises(ParjamError, match=message) as got:
        active.from_rows(COMM, rowio.read_rows(COMM, path))
    assert str(got.value).split(":")[0] == str(serial.value).split(":")[0]
