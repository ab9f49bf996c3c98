"""Files written by row blocks (parjam.files.rowio): every rank's rows land in the right hyperslab in
rank order (pieces, empty ranks, a second axis), rows keyed by scattered ids go home in id
order, a packing file by row blocks equals h5md.write_packing's, and a failure (no space at the
reservation, a write error in the middle of the stream, an error in the caller) leaves no file
and no temporary, with one ParjamError on every rank and no rank left waiting.
1 rank and 2 (the MPI pass)."""

import errno
import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam.files import h5md, rowio
from parjam.pack import staterows
from parjam.net import active
from parjam.errors import ParjamError
from parjam.net.network import analyze, contact_forces
from parjam.net.potential import d2V, overlap

from conftest import DATA

COMM = MPI.COMM_WORLD
REF = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")


@pytest.fixture
def where(shared_tmp, request):
    """A fresh directory every rank sees, for one test."""
    path = os.path.join(shared_tmp, request.node.name.replace("[", "_").replace("]", ""))
    if COMM.rank == 0:
        os.makedirs(path)
    COMM.Barrier()
    return path


def uneven_counts(n):
    """Rows per rank: uneven, rank 1 (if any) holding none."""
    counts = np.zeros(COMM.size, dtype=int)
    counts[0] = n if COMM.size == 1 else n // 3
    if COMM.size > 1:
        counts[-1] += n - counts.sum()
    return counts


@pytest.mark.parametrize("chunk", [rowio.CHUNK_BYTES, 40])
def test_rows_land_in_rank_order(where, chunk):
    n = 37
    counts = uneven_counts(n)
    lo = int(counts[:COMM.rank].sum())
    hi = lo + int(counts[COMM.rank])
    vec = np.arange(n * 3 * 2, dtype=float).reshape(3, n, 2) * 0.5 - 7.0  # rows along axis 1
    ids = np.arange(n, dtype=np.int32)[::-1].copy()
    path = os.path.join(where, "r.h5")
    with rowio.rows_file(COMM, path, vec.nbytes + ids.nbytes, chunk_bytes=chunk) as out:
        out.meta(lambda f, v: f.create_group("g").attrs.__setitem__("v", v), lambda: (1.5,))
        out.rows("g/vec", vec[:, lo:hi], axis=1, attrs={"unit": h5md.fixed_string("tau-1")})
        out.rows("ids", ids[lo:hi])
    COMM.Barrier()
    with h5py.File(path, "r") as f:
        assert np.array_equal(f["g/vec"][()], vec) and f["g/vec"].dtype == vec.dtype
        assert np.array_equal(f["ids"][()], ids) and f["ids"].dtype == np.int32
        assert f["g"].attrs["v"] == 1.5 and f["g/vec"].attrs["unit"] == b"tau-1"
    assert sorted(os.listdir(where)) == ["r.h5"]  # no temporary left
    assert os.path.getsize(path) < vec.nbytes + ids.nbytes + 64 * 1024  # reservation released


def test_home_rows_puts_scattered_ids_in_id_order():
    n = 101
    perm = np.random.default_rng(3).permutation(n)
    mine = perm[COMM.rank::COMM.size]  # any rank may hold any id
    mine = mine[mine % 7 != 0]  # holes: not every id exists (rattlers)
    ids, vals = active.home_rows(COMM, n, mine, np.stack([mine * 10.0, -mine], axis=1))
    start, stop = active.row_block(n, COMM)
    assert np.all((ids >= start) & (ids < stop)) and np.all(np.diff(ids) > 0)
    assert np.array_equal(vals, np.stack([ids * 10.0, -ids], axis=1))
    every = np.concatenate(COMM.allgather(ids))
    assert np.array_equal(every, np.array([k for k in range(n) if k % 7 != 0]))
    alone, none = active.home_rows(COMM, n, mine)
    assert np.array_equal(alone, ids) and none is None


def test_packing_rows_equal_write_packing(where):
    """The streaming writer of a packing file (for the engine) gives h5md.write_packing's
    datasets, dtypes, values and attributes from row blocks."""
    pack = h5md.read_packing(REF)
    net = analyze(pack)
    c = net.all_contacts
    start, stop = active.row_block(pack.n, COMM)
    c0, c1 = active.row_block(len(c), COMM)
    sl = slice(c0, c1)
    fmag = np.linalg.norm(contact_forces(pack, c), axis=1)
    part = staterows.PackingRows(
        pos=pack.pos[start:stop], diam=pack.diam[start:stop],
        species=np.asarray(pack.meta["species"], np.int32)[start:stop]
        if "species" in pack.meta else np.zeros(stop - start, np.int32),
        rattler=net.rattler[start:stop], contacts=np.stack([c.i, c.j], axis=1)[sl],
        overlap=overlap(c.r, c.sigma)[sl], force=fmag[sl],
        stiffness=d2V(c.r, c.sigma, pack.alpha, pack.eps)[sl])
    params, prov = {"protocol": "test", "ladder": ["a", 1]}, {"ranks": 1, "x": {"a": 1}}
    extra = {"hexatic_order_local": 0.25}
    new, old = os.path.join(where, "new.h5"), os.path.join(where, "old.h5")
    rowio.write_packing_rows(COMM, new, part, pack.d, pack.L, pack.alpha, pack.eps, pack.phi,
                             dict(net.summary(), stress_tensor=net.stress, **extra), params, prov)
    if COMM.rank == 0:
        h5md.write_packing(old, pack, net, params, prov, extra)
    COMM.Barrier()
    assert same_content(old, new)


def same_content(pa, pb):
    """Every object, dtype, shape, value and attribute equal (references: by target name)."""
    with h5py.File(pa, "r") as fa, h5py.File(pb, "r") as fb:
        names = []
        fa.visit(names.append)
        other = []
        fb.visit(other.append)
        assert sorted(names) == sorted(other)
        for name in names + ["/"]:
            oa, ob = fa[name], fb[name]
            if isinstance(oa, h5py.Dataset):
                assert oa.dtype == ob.dtype and oa.shape == ob.shape, name
                assert np.array_equal(oa[()], ob[()]), name
            assert sorted(oa.attrs) == sorted(ob.attrs), name
            for key in oa.attrs:
                va, vb = oa.attrs[key], ob.attrs[key]
                if isinstance(va, h5py.Reference):
                    assert fa[va].name == fb[vb].name, (name, key)
                else:
                    assert np.array_equal(np.asarray(va), np.asarray(vb)), (name, key)
    return True


def test_no_space_at_the_reservation_is_one_line_and_no_file(where, monkeypatch):
    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    path = os.path.join(where, "x.h5")
    with pytest.raises(ParjamError, match="cannot write .No space left on device.") as err:
        with rowio.rows_file(COMM, path, 1000) as out:
            out.rows("a", np.zeros(3))
    assert err.value.collective and "\n" not in str(err.value)
    COMM.Barrier()
    assert os.listdir(where) == []


def test_a_write_error_mid_stream_reaches_every_rank(where, monkeypatch):
    """Rank 0 fails to write the first piece; it still receives every rank's pieces (no rank
    waits forever), the error is raised on every rank, no file and no temporary stay."""
    def broken(self, name, axis, first, piece):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(rowio.RowFile, "put", broken)
    path = os.path.join(where, "x.h5")
    with pytest.raises(ParjamError, match=r"x\.h5: cannot write \(Input/output error\)"):
        with rowio.rows_file(COMM, path, 1000, chunk_bytes=16) as out:
            out.rows("a", np.arange(10.0) + COMM.rank)
            out.rows("b", np.arange(4.0))  # never reached on any rank
    COMM.Barrier()
    assert os.listdir(where) == []


def test_an_error_in_the_caller_keeps_the_old_file(where):
    path = os.path.join(where, "x.h5")
    if COMM.rank == 0:
        with h5py.File(path, "w") as f:
            f["old"] = np.ones(2)
    COMM.Barrier()
    with pytest.raises(ZeroDivisionError):
        with rowio.rows_file(COMM, path, 100) as out:
            out.rows("new", np.ones(3))
            1 / 0
    COMM.Barrier()
    with h5py.File(path, "r") as f:
        assert list(f) == ["old"]
    assert os.listdir(where) == ["x.h5"]


@pytest.mark.skipif(COMM.size == 1, reason="blocks of several ranks (the MPI pass)")
def test_blocks_that_disagree_are_refused(where):
    path = os.path.join(where, "x.h5")
    with pytest.raises(ParjamError, match="differ in shape or type"):
        with rowio.rows_file(COMM, path, 100) as out:
            out.rows("a", np.zeros((2, 3 + COMM.rank)))
    COMM.Barrier()
    assert os.listdir(where) == []


def test_space_check_of_the_mpio_path(where):
    """The mpio path (h5py built with MPI, not this machine's: that path itself cannot run
    here) checks the free space of the nearest existing directory before HDF5 creates the
    file."""
    rowio.check_space(os.path.join(where, "not", "yet", "x.h5"), 1)
    with pytest.raises(ParjamError, match=r"x\.h5: cannot write \(No space left on device\)"):
        rowio.check_space(os.path.join(where, "not", "yet", "x.h5"), 1 << 62)
    assert not os.path.exists(os.path.join(where, "not"))
