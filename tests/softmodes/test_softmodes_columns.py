"""The soft-mode count d + q - 1 - (Nc - Nc_iso) and the column-block null-space method (parjam.softmodes.nullspace, ``parjam softmodes
--columns``): blocks of any width span the same null space as the single block (principal
cosines 1), satisfy Eq. 3 and are orthonormal; counts, extensions, f(x) and trial energies agree
to round-off, on 1 rank and on 2; f(x) does not depend on the basis of the null space; a bad
--columns is one line, exit 2, no file.  The out-of-core basis (``--scratch``) gives the in-core
results to round-off and leaves no file behind; a bad scratch directory is one line, exit 2."""

import os
import tempfile

import numpy as np
import pytest

from parjam import cli, env, softmodes as sm
from parjam.files import h5md
from conftest import DATA

PETSc = env.petsc()
ISO = ["ref_d3_mono_N128_dphi1e-06.h5", "ref_d2_bi_N128_dphi1e-06.h5"]
HYPER = ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"]
LARGER = "soft_d3_N512_m0.h5"


@pytest.fixture(scope="module")
def comm():
    return PETSc.COMM_WORLD


def cut_system(name, subdivide=None):
    """The cut system on all ranks (each holds its own rows of the distributed network)."""
    pack = h5md.read_packing(os.path.join(DATA, name))
    planes = (sm.subdivision_planes(subdivide, pack.d) if subdivide
              else [sm.Plane(0, 0.5)])
    return sm.prepare(pack, planes, allow_hyperstatic=True, comm=PETSc.COMM_WORLD)


def bases(comm, cs, widths):
    """The null basis of the cut system for each column width (None: one block)."""
    M = sm.relaxed_matrix(comm, cs, cs.kept)
    scale = cs.scale
    n_soft = sm.null_count(comm, M, scale) - cs.d
    out = {w: sm.null_basis(comm, M, cs.d, n_soft, scale, "block", columns=w) for w in widths}
    S = sm.rigidity_matrix(comm, cs, cs.kept)
    eq3 = {w: sm.eq3_residual(comm, S, nb.V) for w, nb in out.items()}
    S.destroy()
    M.destroy()
    return out, eq3, n_soft, scale


@pytest.mark.parametrize("name,subdivide,widths", [
    (ISO[0], None, (13,)),
    (ISO[1], 2, (16,)),
    (LARGER, None, (64,)),
])
def test_blocks_span_the_single_block_null_space(comm, name, subdivide, widths):
    cs = cut_system(name, subdivide)
    got, eq3, n_soft, scale = bases(comm, cs, (None,) + widths)
    ref = got[None]
    assert n_soft > max(w for w in widths if w < n_soft)  # several blocks really happen
    M = sm.relaxed_matrix(comm, cs, cs.kept)
    T = sm.translation_columns(M, cs.d)
    M.destroy()
    for w in (None,) + widths:
        nb = got[w]
        assert nb.V.shape[1] == n_soft
        assert eq3[w] < 1e-12
        assert sm.orthonormality_error(comm, nb.V) < 1e-12
        assert np.abs(nb.rayleigh).max() < 1e-12 * scale
        assert np.abs(sm.gram(comm, T, nb.V)).max() < 1e-10  # translations deflated
        cos = np.linalg.svd(sm.gram(comm, ref.V, nb.V), compute_uv=False)
        assert np.allclose(cos, 1.0, atol=1e-9), (w, cos.min())
        assert nb.gap == pytest.approx(ref.gap, rel=1e-6) and nb.gap > 1e-6 * scale


@pytest.mark.parametrize("name", ISO + HYPER)
def test_count_is_d_plus_q_minus_1_minus_the_excess(comm, name):
    """Sec. II: the inertia count of the cut system is d + q - 1 - (Nc - Nc_iso), for the
    isostatic packings and for those 7-13 contacts above isostatic."""
    cs = cut_system(name)
    M = sm.relaxed_matrix(comm, cs, cs.kept, fmt="sbaij")
    count = sm.null_count(comm, M, cs.scale)
    M.destroy()
    assert count == cs.expected_general == sm.expected_zero_modes(cs.d, cs.q, cs.excess)
    assert (cs.excess == 0) == (cs.expected == cs.expected_general)


@pytest.mark.parametrize("name", ISO)
def test_fx_is_basis_independent(comm, name):
    """Two bases of the same null space (two column widths, and one rotated by a random
    orthogonal matrix) give the same f(x), with and without the localised modes."""
    cs = cut_system(name, 2)
    got, _, n_soft, _ = bases(comm, cs, (None, 8))
    lo, hi = got[None].lo, got[None].hi
    u = sm.coordinate_from_plane(cs.pos, cs.L, cs.planes[0])  # the owned rows lo..hi-1
    rot, _ = np.linalg.qr(np.random.default_rng(2).normal(size=(n_soft, n_soft)))
    f = [sm.overlap_function(comm, V, u, 10)[1]
         for V in (got[None].V, got[8].V, got[8].V @ rot)]
    f_nt = [sm.overlap_without_localised(comm, cs, V, lo, hi, u, 10)[1]
            for V in (got[None].V, got[8].V, got[8].V @ rot)]
    for a in f[1:]:
        assert np.allclose(a, f[0], atol=1e-12)
    for a in f_nt[1:]:
        assert np.allclose(a, f_nt[0], atol=1e-12)
    # the row-chunked f without localised modes is that of the explicit basis
    W = sm.without_localised(comm, cs, got[8].V, lo, hi)
    assert np.allclose(sm.overlap_function(comm, W, u, 10)[1], f_nt[0], atol=1e-12)
    assert np.sum(f[0]) / 10 == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", ISO)
def test_analysis_in_blocks_equals_the_single_block(comm, name):
    """The whole analysis with 8-column blocks on all ranks against one block on COMM_SELF:
    counts, extension spectrum, f(x), trial energies and the variational count."""
    cs = cut_system(name, 2)
    a = sm.analyze(PETSc.COMM_SELF, cs, e0=0.1, columns=None)
    b = sm.analyze(comm, cs, e0=0.1, columns=8)
    assert a.count == b.count == cs.expected and a.n_soft == b.n_soft
    assert a.q_prime == b.q_prime and a.n_below == b.n_below
    assert np.allclose(a.e, b.e, atol=1e-11)
    assert np.allclose(a.overlap, b.overlap, atol=1e-11)
    assert np.allclose(a.trial_energy, b.trial_energy, rtol=1e-8, equal_nan=True)
    assert np.array_equal(a.fractions, b.fractions)
    assert b.eq3 < 1e-12 and b.ortho < 1e-12
    assert b.solver["columns"] == 8 and a.solver["columns"] == 0


@pytest.fixture(scope="module")
def tmpdir_all():
    mpi = PETSc.COMM_WORLD.tompi4py()
    path = mpi.bcast(tempfile.mkdtemp(prefix="parjam-cols-") if mpi.Get_rank() == 0 else None)
    yield path
    mpi.Barrier()
    if mpi.Get_rank() == 0:
        import shutil

        shutil.rmtree(path, ignore_errors=True)


def test_cli_columns_is_recorded_and_changes_no_result(comm, tmpdir_all):
    import h5py

    src = os.path.join(DATA, ISO[0])
    outs = [os.path.join(tmpdir_all, f"cols{w}.h5") for w in (8, 100000)]
    for w, out in zip((8, 100000), outs):
        assert cli.main(["softmodes", src, "--subdivide", "2", "--columns", str(w), "-q",
                         "--out", out]) == 0
    comm.tompi4py().Barrier()
    with h5py.File(outs[0], "r") as f, h5py.File(outs[1], "r") as g:
        assert f["softmodes"].attrs["columns"] == 8 and g["softmodes"].attrs["columns"] == 100000
        assert int(f["softmodes/count"][()]) == int(g["softmodes/count"][()])
        assert np.allclose(f["softmodes/overlap"][()], g["softmodes/overlap"][()], atol=1e-11)
        assert np.allclose(f["softmodes/extension"][()], g["softmodes/extension"][()],
                           atol=1e-11)


@pytest.mark.parametrize("bad", ["0", "-3", "100001"])
def test_bad_columns_is_one_line_exit_2_and_no_file(comm, tmpdir_all, capsys, bad):
    out = os.path.join(tmpdir_all, f"bad{bad}.h5")
    capsys.readouterr()
    code = cli.main(["softmodes", os.path.join(DATA, ISO[0]), "--cut", "x=0.5",
                     "--columns", bad, "-q", "--out", out])
    err = capsys.readouterr().err
    assert code == 2 and not os.path.exists(out)
    if comm.getRank() == 0:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("parjam: error:")
        assert "--columns must lie in [1, 100000]" in lines[0]


def test_each_column_block_starts_from_its_columns_of_one_matrix():
    """The random start of a block is the block's columns of one global matrix, whatever the
    row split and the column blocks (tiles of 3072 rows x 64 columns, each with its own seed)."""
    whole = sm.random_block(0, 7000, 150, seed=4)
    for first, k in [(0, 13), (13, 64), (77, 73), (60, 8)]:
        parts = np.concatenate([sm.random_block(a, z, k, seed=4, first=first)
                                for a, z in [(0, 3000), (3000, 3072), (3072, 7000)]])
        assert np.array_equal(parts, whole[:, first:first + k])


def test_scratch_basis_reads_and_writes_like_an_array():
    """The on-disk basis: blocks appended, row slices read and written, columns and column
    blocks read back, exactly as the same array in memory."""
    rng = np.random.default_rng(5)
    ref = rng.standard_normal((37, 23))
    path = tempfile.mkdtemp(prefix="parjam-scratch-test-")  # this rank's own
    space = sm.ScratchSpace(path)
    V = space.basis(37)
    for a, z in [(0, 8), (8, 16), (16, 23)]:
        V.append(ref[:, a:z])
    assert V.shape == (37, 23)
    assert np.array_equal(V[0:37], ref) and np.array_equal(V[5:11], ref[5:11])
    assert np.array_equal(V[30:100], ref[30:]) and V[37:40].shape == (0, 23)
    assert np.array_equal(V.columns(6, 19), ref[:, 6:19])
    assert np.array_equal(V.columns(16, 64), ref[:, 16:])
    assert np.array_equal(np.concatenate(list(V.column_blocks()), axis=1), ref)
    U, _ = np.linalg.qr(rng.standard_normal((23, 23)))
    V[3:20] = V[3:20] @ U
    ref[3:20] = ref[3:20] @ U
    assert np.array_equal(V[0:37], ref)
    with pytest.raises(TypeError):
        V[::2]
    space.close()
    assert not os.path.exists(path)


def test_scratch_space_is_removed_on_error(comm):
    with tempfile.TemporaryDirectory(prefix="parjam-scratch-test-") as top:
        with pytest.raises(RuntimeError):
            with sm.scratch_space(comm, top) as space:
                space.basis(4).append(np.ones((4, 2)))
                assert os.listdir(top) == [os.path.basename(space.path)]
                assert len(os.listdir(space.path)) == 1
                raise RuntimeError("boom")
        assert os.listdir(top) == []


@pytest.mark.parametrize("name", ISO)
def test_out_of_core_analysis_equals_in_core(comm, name, tmpdir_all):
    """--scratch: the basis on disk, read back in column blocks and row chunks, gives the
    in-core result to round-off (same columns), on every rank count; its files are removed."""
    cs = cut_system(name, 2)
    a = sm.analyze(comm, cs, e0=0.1, columns=8)
    with sm.scratch_space(comm, tmpdir_all) as space:
        b = sm.analyze(comm, cs, e0=0.1, columns=8, scratch=space)
        assert isinstance(b.V, sm.ScratchBasis) and b.V.shape == a.V.shape
        assert os.path.getsize(b.V.path) == a.V.size * 8  # the whole basis is on disk
        Vb = b.V[0:b.V.shape[0]]
        mine = space.path
    assert not os.path.exists(mine)
    assert a.count == b.count and a.n_soft == b.n_soft
    assert a.q_prime == b.q_prime and a.n_below == b.n_below
    assert np.allclose(a.e, b.e, atol=1e-11)
    assert np.allclose(a.overlap, b.overlap, atol=1e-11)
    assert np.allclose(a.trial_energy, b.trial_energy, rtol=1e-8, equal_nan=True)
    assert np.allclose(a.modulated_energy, b.modulated_energy, atol=1e-10)
    assert b.gap == pytest.approx(a.gap, rel=1e-6)
    assert b.eq3 < 1e-12 and b.ortho < 1e-12
    # the extended bases agree up to signs within the (nondegenerate) extension spectrum
    cos = np.abs(np.diag(sm.gram(comm, a.V, Vb)))
    simple = np.diff(a.e, prepend=-1, append=2).clip(None, 1)
    simple = np.minimum(simple[:-1], simple[1:]) > 1e-6
    assert np.allclose(cos[simple], 1.0, atol=1e-8)
    assert b.solver["out_of_core"] and not a.solver["out_of_core"]


def test_cli_scratch_changes_no_result_and_leaves_nothing(comm, tmpdir_all):
    import h5py

    src = os.path.join(DATA, ISO[0])
    scratch = os.path.join(tmpdir_all, "scratch")
    if comm.getRank() == 0:
        os.makedirs(scratch, exist_ok=True)
    comm.tompi4py().Barrier()
    outs = [os.path.join(tmpdir_all, f"ooc{i}.h5") for i in range(2)]
    for extra, out in zip(([], ["--scratch", scratch]), outs):
        assert cli.main(["softmodes", src, "--subdivide", "2", "--columns", "8", "--vectors",
                         "-q", "--out", out] + extra) == 0
    comm.tompi4py().Barrier()
    assert os.listdir(scratch) == []
    with h5py.File(outs[0], "r") as f, h5py.File(outs[1], "r") as g:
        assert g["softmodes"].attrs["out_of_core"] and not f["softmodes"].attrs["out_of_core"]
        for key in ("extension", "overlap", "extended_fraction"):
            assert np.allclose(f["softmodes"][key][()], g["softmodes"][key][()], atol=1e-11)
        P = [np.einsum("bia,bjc->iajc", h["softmodes/basis"][()], h["softmodes/basis"][()])
             for h in (f, g)]  # the projector on the soft space, basis-independent
        assert np.allclose(P[0], P[1], atol=1e-10)


@pytest.mark.parametrize("bad,message", [
    (["--scratch", "MISSING"], "not a directory"),
    (["--scratch", "FILE"], "not a directory"),
    (["--scratch", "DIR", "--basis", "krylov"], "--scratch needs --basis block"),
])
def test_bad_scratch_is_one_line_exit_2_and_no_file(comm, tmpdir_all, capsys, bad, message):
    where = {"MISSING": os.path.join(tmpdir_all, "missing", "dir"),
             "FILE": os.path.join(DATA, ISO[0]), "DIR": tmpdir_all}
    out = os.path.join(tmpdir_all, "badscratch.h5")
    capsys.readouterr()
    code = cli.main(["softmodes", os.path.join(DATA, ISO[0]), "--cut", "x=0.5", "-q",
                     "--out", out] + [where.get(x, x) for x in bad])
    err = capsys.readouterr().err
    assert code == 2 and not os.path.exists(out)
    if comm.getRank() == 0:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("parjam: error:")
        assert message in lines[0]


def test_column_blocks_report_their_progress(comm):
    """Each column block reports the null vectors found so far (block_progress prints at most
    once per interval, never the last block, which the analysis reports itself)."""
    from parjam.softmodes.analysis import block_progress

    cs = cut_system(ISO[0])
    M = sm.relaxed_matrix(comm, cs, cs.kept)
    n_soft = sm.null_count(comm, M, cs.scale) - cs.d
    seen = []
    sm.null_basis(comm, M, cs.d, n_soft, cs.scale, "block", columns=13, progress=seen.append)
    M.destroy()
    assert seen == [min(13 * (i + 1), n_soft) for i in range(-(-n_soft // 13))]
    lines = []
    report = block_progress(lines.append, n_soft, every=0.0)
    for found in seen:
        report(found)
    assert len(lines) == len(seen) - 1 and lines[0].startswith(f"null space: 13 of {n_soft}")
    quiet = []
    report = block_progress(quiet.append, n_soft, every=3600.0)
    for found in seen:
        report(found)
    assert quiet == []
