"""A packing protocol state as each rank's rows (parjam.pack.staterows) and its file by row blocks,
against the serial network.analyze + h5md.write_packing of the whole packing: on any number of
ranks (1, 2 in the MPI pass, 3 in one serial test) every per-particle and per-contact dataset
bit for bit, the observables (exact sums, parjam.net.exactsum) to the round-off of the serial
numpy sums.  2D bidisperse (hexatic
order) and 3D monodisperse packings of tests/data."""

import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam.files import h5md
from parjam.net import order
from parjam.pack import staterows
from parjam.net.active import row_block
from parjam.net.network import analyze
from parjam.study.members import write_state

from conftest import DATA, run_on_ranks

COMM = MPI.COMM_WORLD
PACKINGS = ["ref_d2_bi_N128_dphi1e-03.h5", "soft_d2_N256_m1.h5", "ref_d3_mono_N128_dphi1e-06.h5",
            "soft_d3_N256_m0.h5"]
PARAMS = {"state": "test", "member": 0}
EXTRA = {"stable": np.int8(1)}


def state_rows(pack):
    """The packing's contiguous id block of this rank as StateRows (the Jammer's layout)."""
    lo, hi = row_block(pack.n, COMM)
    meta = {"species": np.asarray(pack.meta.get("species", np.zeros(pack.n)))[lo:hi]}
    return staterows.StateRows(COMM, pack.n, pack.L, pack.alpha, pack.eps, pack.phi, lo,
                               pack.pos[lo:hi].copy(), pack.diam[lo:hi].copy(), meta,
                               frozenset(meta))


def datasets(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda k, o: out.__setitem__(k, (o[()] if isinstance(o, h5py.Dataset)
                                                      else None, dict(o.attrs))))
    return out


@pytest.mark.parametrize("name", PACKINGS)
def test_file_by_rows_is_the_serial_file(name, shared_tmp):
    pack = h5md.read_packing(os.path.join(DATA, name))
    rows = state_rows(pack)
    net = rows.network()
    hexatic = staterows.hexatic_order(rows, net)
    ref_hex = order.hexatic_order(pack)
    if pack.d == 2:
        assert np.allclose(hexatic, ref_hex, rtol=1e-12)
    else:
        assert np.isnan(hexatic).all()
    new = os.path.join(shared_tmp, f"rows-{name}")
    write_state(new, rows, net, PARAMS, {"ranks": 1}, dict(EXTRA, hexatic=hexatic[0]))
    if COMM.Get_rank() == 0:
        ref = os.path.join(shared_tmp, f"serial-{name}")
        h5md.write_packing(ref, pack, analyze(pack), PARAMS, {"ranks": 1},
                         dict(EXTRA, hexatic=ref_hex[0]))
        a, b = datasets(ref), datasets(new)
        assert a.keys() == b.keys()
        for key, (va, attrs_a) in a.items():
            vb, attrs_b = b[key]
            assert attrs_a.keys() == attrs_b.keys(), key
            if va is None:
                continue
            assert va.dtype == vb.dtype and va.shape == vb.shape, key
            # sums over particles or contacts (observables) are exact sums: the serial numpy
            # sums' values to round-off; the per-particle and per-contact data bitwise
            if not key.startswith("observables") or va.dtype.kind not in "fc":
                assert np.array_equal(va, vb, equal_nan=va.dtype.kind in "fc"), key
            else:
                assert np.allclose(va, vb, rtol=1e-10, atol=1e-14, equal_nan=True), key
    COMM.Barrier()


def test_rows_hold_only_their_block():
    """No rank holds more than its block of the particles, nor its contacts' share."""
    pack = h5md.read_packing(os.path.join(DATA, "soft_d3_N256_m0.h5"))
    rows = state_rows(pack)
    part = staterows.packing_rows(rows, rows.network())
    lo, hi = row_block(pack.n, COMM)
    assert len(part.pos) == hi - lo
    assert np.all((part.contacts[:, 0] >= lo) & (part.contacts[:, 0] < hi))
    assert COMM.allreduce(len(part.contacts)) == len(analyze(pack).all_contacts)
    whole = rows.packing()  # the explicit gather still gives the packing back
    assert np.array_equal(whole.pos, pack.pos) and np.array_equal(whole.diam, pack.diam)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """A middle rank whose id block's contacts come from slabs on both sides."""
    res = run_on_ranks("test_staterows.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
