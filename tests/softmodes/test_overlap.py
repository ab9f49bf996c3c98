"""The overlap function f(x) of the soft modes (parjam.softmodes.overlap_function; Wyart et al.
2005, Sec. III), for both cut geometries of docs/results/reproduction.md section 12 (one plane at
x = L/2, and all faces of the cube: ``subdivide = 1``) on the isostatic reference packing.

The definition parjam uses: f(u) = n_soft^-1 sum_b sum_{i: u_i in slab} |dR_i,b|^2 / du, u = x/L
from the first plane in [0, 1), du = 1/bins, the sum over an orthonormal basis of the soft modes
without the translations.  So sum_slabs f du = 1 exactly (the basis is orthonormal), and f is
the trace of the soft-space projector per slab: the same for every orthonormal basis of the
same space.  Checked here against a dense SVD null space (projector built directly), against a
random rotation of the basis, against SLEPc's Krylov basis, and 1 rank against all ranks."""

import json
import os
import shutil
import sys

import numpy as np
import pytest

from parjam import cli, env, softmodes as sm
from parjam.files import h5md
from parjam.testing import softmodes_reference as ref

from conftest import DATA, ROOT

PETSc = env.petsc()
WORLD = PETSc.COMM_WORLD
SELF = PETSc.COMM_SELF
PACKING = "ref_d3_mono_N128_dphi1e-06.h5"  # isostatic after rattler removal
GEOMETRIES = {"plane": (["x=0.5"], None, 0.1), "faces": ([], 1, 0.05)}
BINS = 10


@pytest.fixture(scope="module")
def pack():
    return h5md.read_packing(os.path.join(DATA, PACKING))


def planes(pack, geo):
    cuts, sub, _ = GEOMETRIES[geo]
    out = [sm.parse_cut(t, pack.d) for t in cuts]
    if sub is not None:
        out += sm.subdivision_planes(sub, pack.d)
    return out


_CACHE = {}


def analysed(comm, pack, geo, basis="block"):
    key = (geo, basis, comm.getSize())
    if key not in _CACHE:
        cs = sm.prepare(pack, planes(pack, geo), comm=comm)
        _CACHE[key] = sm.analyze(comm, cs, e0=GEOMETRIES[geo][2], nbins=BINS, basis=basis)
    return _CACHE[key]


def gathered(comm, V):
    return np.concatenate(comm.tompi4py().allgather(np.asarray(V)), axis=0)


@pytest.mark.parametrize("geo", sorted(GEOMETRIES))
def test_geometry_counts_and_f_integrates_to_one(pack, geo):
    """Both geometries cut an isostatic packing: null space d + q - 1; f and f without the
    trivially localised modes integrate to 1 over x/L (the normalisation by n_soft)."""
    res = analysed(WORLD, pack, geo)
    cs = res.cs
    assert cs.isostatic and res.count == cs.expected == cs.d + cs.q - 1
    if geo == "faces":
        assert sorted(p.label for p in cs.planes) == ["x=0", "y=0", "z=0"]
        assert res.e.max() <= 1.0 and sm.gradient_bound(cs.L, cs.planes) == pytest.approx(
            3 * (np.pi / cs.L) ** 2)
    u, f, f_nt = res.overlap.T
    assert np.allclose(np.diff(u), 1.0 / BINS) and u[0] == pytest.approx(0.5 / BINS)
    assert np.sum(f) / BINS == pytest.approx(1.0, abs=1e-12)
    assert np.sum(f_nt) / BINS == pytest.approx(1.0, abs=1e-12)
    assert res.c_bound == pytest.approx(f.min()) and 0 < res.c_bound < 1


@pytest.mark.parametrize("geo", sorted(GEOMETRIES))
def test_f_is_the_projector_trace_of_a_dense_null_space(pack, geo):
    """f from the dense SVD null space of the cut rigidity matrix (the projector onto it minus
    the translations, no basis of parjam's) equals parjam's f to round-off."""
    res = analysed(WORLD, pack, geo)
    w = res.cs.gathered()
    dim, N0, _ = ref.dense_null_space(ref.dense_rigidity(w, w.kept))
    assert dim == res.count
    T = np.kron(np.ones((w.n, 1)), np.eye(w.d)) / np.sqrt(w.n)
    diag = np.einsum("ij,ij->i", N0, N0) - np.einsum("ij,ij->i", T, T)  # diag of P_soft
    u = sm.coordinate_from_plane(w.pos, w.L, res.cs.planes[0])
    slab = np.minimum((u * BINS).astype(int), BINS - 1)
    f_dense = np.bincount(slab, weights=diag.reshape(w.n, w.d).sum(axis=1),
                          minlength=BINS) * BINS / (dim - w.d)
    assert np.allclose(res.overlap[:, 1], f_dense, atol=1e-9)


@pytest.mark.parametrize("geo", sorted(GEOMETRIES))
def test_f_is_basis_independent(pack, geo):
    """Three other orthonormal bases of the same soft space give the same f to round-off: a
    random orthogonal rotation of the computed basis (the same rotation on every rank), SLEPc's
    Krylov-Schur basis, and the basis computed on one rank (the distributed one on 2 ranks)."""
    res = analysed(WORLD, pack, geo)
    cs = res.cs
    f = res.overlap[:, 1]
    u = sm.coordinate_from_plane(cs.pos, cs.L, cs.planes[0])  # the owned rows
    rot, _ = np.linalg.qr(np.random.default_rng(7).normal(size=(res.n_soft, res.n_soft)))
    _, f_rot = sm.overlap_function(WORLD, res.V @ rot, u, BINS)
    assert np.abs(f_rot - f).max() < 1e-12
    kry = analysed(WORLD, pack, geo, basis="krylov")
    assert np.abs(kry.overlap[:, 1] - f).max() < 1e-9
    one = analysed(SELF, pack, geo)  # every rank alone
    assert one.count == res.count
    assert np.abs(one.overlap[:, 1] - f).max() < 1e-10
    assert np.abs(one.overlap[:, 2] - res.overlap[:, 2]).max() < 1e-10
    # the bases themselves differ (rotation) but span the same space
    Vw, Vs = gathered(WORLD, res.V), np.asarray(one.V)
    if WORLD.getSize() == 1:
        assert np.allclose(np.linalg.svd(Vw.T @ Vs, compute_uv=False), 1.0, atol=1e-9)


def test_uniform_modes_give_f_one_and_the_cube_has_soft_modes_at_its_faces(pack):
    """f of an exactly uniform space (the d translations, normalised) is 1 in every slab up to
    the sampling of the particles per slab; on the cut cube the soft modes gather at the cut
    faces: the two slabs touching x = 0 hold more than the average."""
    res = analysed(WORLD, pack, "faces")
    cs = res.cs
    u = sm.coordinate_from_plane(cs.pos, cs.L, cs.planes[0])
    T = np.kron(np.ones((len(u), 1)), np.eye(cs.d)) / np.sqrt(cs.n)
    _, f_t = sm.overlap_function(WORLD, T, u, BINS)
    counts = np.bincount(np.minimum((u * BINS).astype(int), BINS - 1), minlength=BINS)
    counts = WORLD.tompi4py().allreduce(counts)
    assert np.allclose(f_t, counts * BINS / cs.n, atol=1e-12)
    f = res.overlap[:, 1]
    assert f[0] + f[-1] > 2.0


def test_fx_vs_n_collects_cut_files_and_the_figure_draws_them(shared_tmp):
    """scripts/fx_vs_n.py's layout on two isostatic packings of tests/data (N = 256, 512), both
    geometries cut by ``parjam softmodes``: ``collect`` reads back the files' f(x) and c
    (never recomputing them), its means are the members' values, and ``parjam plot`` draws the
    JSON."""
    sys.path.insert(0, os.path.join(ROOT, "scripts"))
    import fx_vs_n

    mpi = WORLD.tompi4py()
    root = os.path.join(shared_tmp, "fxn")
    for n, name in ((256, "soft_d3_N256_m0.h5"), (512, "soft_d3_N512_m0.h5")):
        base = fx_vs_n.size_dir(root, n, None)
        packdir, cutdir = os.path.join(base, "packings"), os.path.join(base, "cuts")
        if mpi.Get_rank() == 0:
            os.makedirs(packdir)
            os.makedirs(cutdir)
            shutil.copy(os.path.join(DATA, name),
                        os.path.join(packdir, "member0000_dphi1.0e-08.h5"))
            fx_vs_n.save(os.path.join(base, "costs.json"),
                         {"N": n, "seed": n, "dphi": 1e-8, "members": {"0": {"excess": 0}}})
        mpi.Barrier()
        for geo, (extra, e0) in fx_vs_n.GEOMETRIES.items():
            assert cli.main(["softmodes", os.path.join(packdir, "member0000_dphi1.0e-08.h5"),
                             *extra, "--e0", str(e0), "-q",
                             "--out", os.path.join(cutdir, f"m0_{geo}.h5")]) == 0
    out = os.path.join(root, "results.json")
    if mpi.Get_rank() == 0:
        fx_vs_n.main(["collect", "--root", root, "--out", out])
    mpi.Barrier()
    res = json.load(open(out))
    assert res["packs"]["256"]["isostatic"] == 1
    assert res["packs"]["256"]["dphi"] == [1e-8]
    for geo in fx_vs_n.GEOMETRIES:
        per = res["summary"][geo]["per_N"]
        assert sorted(per) == ["256", "512"]
        for n in ("256", "512"):
            cut = [m for m in res["members"] if m["N"] == int(n)][0]["cuts"][geo]
            assert per[n]["c"] == pytest.approx(min(cut["f"])) == pytest.approx(cut["c"])
            assert sum(per[n]["f"]) / len(per[n]["f"]) == pytest.approx(1.0, abs=1e-12)
            assert 0.0 <= per[n]["qpq_0.1"] <= 1.0
        assert set(res["summary"][geo]["fit_against_L"]) >= {"omega_t2", "c"}
    png = os.path.join(root, "fx.png")
    assert cli.main(["plot", out, "--out", png, "-q"]) == 0
    assert os.path.getsize(png) > 10_000


def test_fx_vs_n_auto_dphi_keeps_the_expected_excess_of_n4096():
    """``--dphi auto``: 1e-8 up to N = 4096, then N dphi^(1/2) (the expected Nc - Nc_iso by
    Eq. 22) held at its N = 4096 value; a number is taken as given."""
    sys.path.insert(0, os.path.join(ROOT, "scripts"))
    import fx_vs_n

    assert fx_vs_n.dphi_for(1024, "auto") == fx_vs_n.dphi_for(4096, "auto") == 1e-8
    for n in (16384, 65536):
        assert n * fx_vs_n.dphi_for(n, "auto") ** 0.5 == pytest.approx(4096 * 1e-4, rel=1e-12)
    assert fx_vs_n.dphi_for(65536, 3e-9) == 3e-9
