"""Soft modes after plane cuts (parjam.softmodes): the null-space count against a dense SVD and the
independent reference counts, Eq. 3 residuals and orthonormality of the SLEPc basis, the
extension and f(x), the extended subspace, the trial modes against Eq. (kkk) and the true
spectrum, their 1/L^2 scaling, 1 rank against 2 ranks, and bad input through the CLI."""

import glob
import json
import os
import tempfile

import numpy as np
import pytest

from parjam import cli, env, softmodes as sm
from parjam.files import h5md
from parjam.net import network
from parjam.errors import ParjamError
from parjam.testing import softmodes_reference as ref
from conftest import DATA

PETSc = env.petsc()
REF = {r["file"]: r for r in json.load(open(os.path.join(DATA, "reference.json")))}
ISO = ["ref_d3_mono_N128_dphi1e-06.h5", "ref_d2_bi_N128_dphi1e-06.h5"]
HYPER = ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"]
CUTS = {"one": ["x=0.5"], "two axes": ["x=0.5", "y=0.25"], "wrap": ["x=0"],
        "parallel": ["x=0.2", "x=0.7"], "sub-boxes": ("subdivide", 2)}


@pytest.fixture(scope="session")
def comm():
    return PETSc.COMM_WORLD


@pytest.fixture(scope="session")
def packs():
    return {name: h5md.read_packing(os.path.join(DATA, name)) for name in REF}


@pytest.fixture(scope="session")
def tmpdir_all():
    """A directory every rank sees (rank 0 makes it)."""
    mpi = PETSc.COMM_WORLD.tompi4py()
    path = mpi.bcast(tempfile.mkdtemp(prefix="parjam-soft-") if mpi.Get_rank() == 0 else None)
    yield path
    mpi.Barrier()
    if mpi.Get_rank() == 0:
        import shutil

        shutil.rmtree(path, ignore_errors=True)


def planes(pack, texts):
    if texts[0] == "subdivide":
        return sm.subdivision_planes(texts[1], pack.d)
    return [sm.parse_cut(t, pack.d) for t in texts]


def gathered(comm, V):
    """All rows of a distributed block of columns, on every rank."""
    return np.concatenate(comm.tompi4py().allgather(V), axis=0)


_CACHE = {}


def analysed(comm, pack, texts, allow=False):
    key = (id(pack), tuple(texts), id(comm))
    if key not in _CACHE:
        cs = sm.prepare(pack, planes(pack, texts), allow_hyperstatic=allow, comm=comm)
        _CACHE[key] = sm.analyze(comm, cs, e0=0.1)
    return _CACHE[key]


# --------------------------------------------------------------------------- cutting

def test_crossing_catches_bonds_that_wrap_across_the_box_edge():
    L = 10.0
    x = np.array([0.2, 9.9, 4.9, 5.1, 3.0])
    r = np.array([-0.5, 0.3, 0.3, 0.3, 0.5])
    assert sm.crossing(x, r, L, 0.0).tolist() == [True, True, False, False, False]
    assert sm.crossing(x, r, L, 5.0).tolist() == [False, False, True, False, False]
    # the bond and its reverse agree
    assert np.array_equal(sm.crossing(x, r, L, 5.0), sm.crossing(np.mod(x + r, L), -r, L, 5.0))


def test_parse_cut_and_subdivision():
    assert sm.parse_cut(" y = 0.25", 3) == sm.Plane(1, 0.25)
    assert len(sm.subdivision_planes(3, 2)) == 6
    for bad in ("z=0.5", "x=1.0", "x=-0.1", "x0.5", "w=0.2", "x=nan"):
        with pytest.raises(ParjamError):
            sm.parse_cut(bad, 2)


@pytest.mark.parametrize("name", sorted(REF))
def test_cut_and_count_match_the_independent_reference(comm, packs, name):
    """q and the null-space dimension after cutting x = L/2 (dense SVD of an independent code)."""
    ref = REF[name]["cut_plane_x_half"]
    cs = sm.prepare(packs[name], planes(packs[name], ["x=0.5"]), allow_hyperstatic=True,
                    comm=comm)
    assert cs.q == ref["q"] and cs.n == ref["Nprime"] and cs.n_contacts == ref["Nc"]
    M = sm.relaxed_matrix(comm, cs, cs.kept, fmt="sbaij")
    count = sm.null_count(comm, M, cs.scale)
    M.destroy()
    assert count == ref["n_zero"]
    if cs.isostatic:
        assert count == cs.expected == ref["expected_if_isostatic"]


@pytest.mark.parametrize("cut", sorted(CUTS))
@pytest.mark.parametrize("name", ISO + HYPER[:1])
def test_count_and_basis_against_dense_svd(comm, packs, name, cut):
    """Null-space dimension = dense-SVD count; the SLEPc basis spans the dense null space minus
    the translations, satisfies Eq. 3 to round-off and is orthonormal."""
    pack = packs[name]
    res = analysed(comm, pack, CUTS[cut], allow=name in HYPER)
    cs = res.cs
    w = cs.gathered()
    S = ref.dense_rigidity(w, w.kept)
    dim, N0, s = ref.dense_null_space(S)
    assert res.count == dim
    rank = cs.n * cs.d - dim
    assert s[rank - 1] > 1e-4 * s[0] and np.all(s[rank:] < 1e-12 * s[0])  # a clear gap
    if cs.isostatic:
        assert res.count == cs.expected
    V = gathered(comm, res.V)
    assert V.shape == (cs.n * cs.d, res.count - cs.d)
    assert res.eq3 < 1e-12 and np.abs(S @ V).max() < 1e-12
    assert res.ortho < 1e-12 and np.abs(V.T @ V - np.eye(V.shape[1])).max() < 1e-12
    T = np.kron(np.ones((cs.n, 1)), np.eye(cs.d)) / np.sqrt(cs.n)
    assert np.abs(T.T @ V).max() < 1e-10
    # [V, T] and the dense null basis span the same space: all principal cosines are 1
    cos = np.linalg.svd(N0.T @ np.hstack([V, T]), compute_uv=False)
    assert np.allclose(cos, 1.0, atol=1e-9)


def test_trivially_localised_modes_are_in_the_soft_space(comm, packs):
    """A particle left with fewer than d contacts moves alone perpendicular to them: that motion
    satisfies Eq. 3 and lies in span(basis, translations)."""
    pack = packs[ISO[0]]
    res = analysed(comm, pack, CUTS["one"])
    cs = res.cs
    w = cs.gathered()
    assert cs.localised == 3 and len(w.localised_particles) > 0
    S = ref.dense_rigidity(w, w.kept)
    V = gathered(comm, res.V)
    T = np.kron(np.ones((cs.n, 1)), np.eye(cs.d)) / np.sqrt(cs.n)
    Q = np.hstack([V, T])
    found = 0
    for p in w.localised_particles:
        rows = S[:, p * cs.d:(p + 1) * cs.d]
        normals = rows[np.abs(rows).sum(axis=1) > 0]
        _, sv, Wt = np.linalg.svd(normals, full_matrices=True)
        for w in Wt[len(sv):]:
            v = np.zeros(cs.n * cs.d)
            v[p * cs.d:(p + 1) * cs.d] = w
            assert np.abs(S @ v).max() < 1e-14
            assert np.linalg.norm(v - Q @ (Q.T @ v)) < 1e-10
            found += 1
    assert found == cs.localised
    # the soft space without them: orthonormal, orthogonal to them, of dimension n_soft - 3
    W = gathered(comm, sm.without_localised(comm, cs, res.V, res.lo, res.hi))
    assert W.shape[1] == res.n_soft - cs.localised
    assert np.abs(W.T @ W - np.eye(W.shape[1])).max() < 1e-12 and np.abs(S @ W).max() < 1e-12
    L = np.zeros((cs.n * cs.d, cs.localised))
    for k, (p, u) in enumerate(sm.all_localised_vectors(cs)):
        L[p * cs.d:(p + 1) * cs.d, k] = u
    assert np.abs(W.T @ np.hstack([L, T])).max() < 1e-12


# --------------------------------------------------------------------------- extension, f(x)

def test_extension_of_a_uniform_translation_is_one_half(comm, packs):
    # exactly 1/2 for particles equally spaced along the cut axis
    pos = np.zeros((40, 2))
    pos[:, 0] = np.arange(40) * 0.25
    g = sm.modulation(pos, 10.0, [sm.Plane(0, 0.3)])
    t = np.repeat(np.eye(2)[:1], 40, axis=0).reshape(-1, 1) / np.sqrt(40)
    assert sm.extension(PETSc.COMM_SELF, t, g**2)[0] == pytest.approx(0.5, abs=1e-14)
    # a packing: the mean of sin^2 over N' particles, 1/2 within its sampling error
    res = analysed(comm, packs[ISO[1]], CUTS["one"])
    cs = res.cs
    lo, hi = res.lo, res.hi
    t = np.zeros(((hi - lo) * cs.d, 1))
    t[0::cs.d] = 1.0 / np.sqrt(cs.n)
    g = sm.modulation(cs.pos, cs.L, cs.planes)  # the owned rows lo..hi-1
    e = sm.extension(comm, t, g**2)[0]
    g_all = sm.modulation(cs.gathered().pos, cs.L, cs.planes)
    assert e == pytest.approx(np.mean(g_all**2), abs=1e-13)
    assert abs(e - 0.5) < 3 * np.std(g_all**2) / np.sqrt(cs.n)


def test_modulation_vanishes_on_every_plane_and_bounds_its_gradient():
    L = 7.0
    cuts = [sm.Plane(0, 0.2), sm.Plane(0, 0.7), sm.Plane(1, 0.0)]
    on = np.array([[0.2 * L, 3.1], [0.7 * L, 1.0], [2.0, 0.0], [5.5, L - 1e-15]])
    assert np.abs(sm.modulation(on, L, cuts)).max() < 1e-14
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, L, (2, 4000, 2))
    b = a + 1e-6 * (b - a)
    grad = np.abs(sm.modulation(b, L, cuts) - sm.modulation(a, L, cuts)) / np.linalg.norm(b - a,
                                                                                        axis=1)
    assert grad.max() <= np.sqrt(sm.gradient_bound(L, cuts)) * (1 + 1e-5)
    assert sm.gradient_bound(L, cuts) == pytest.approx((np.pi / 3.5) ** 2 + (np.pi / 7) ** 2)


@pytest.mark.parametrize("name", ISO)
def test_overlap_function_integrates_to_one_and_is_basis_independent(comm, packs, name):
    res = analysed(comm, packs[name], CUTS["one"])
    u, f = res.overlap[:, 0], res.overlap[:, 1]
    assert np.sum(f) * (u[1] - u[0]) == pytest.approx(1.0, abs=1e-12)
    assert np.sum(res.overlap[:, 2]) * (u[1] - u[0]) == pytest.approx(1.0, abs=1e-12)
    rot, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(res.n_soft, res.n_soft)))
    cs = res.cs
    x = sm.coordinate_from_plane(cs.pos, cs.L, cs.planes[0])
    _, f_rot = sm.overlap_function(comm, res.V @ rot, x, len(u))
    assert np.allclose(f_rot, f, atol=1e-12)
    assert res.c_bound == pytest.approx(f.min())


@pytest.mark.parametrize("name", ISO)
def test_extended_subspace_equals_the_appendix_peeling(comm, packs, name):
    """Diagonalising the projected G gives the same q' as removing, one at a time, the mode of
    smallest <dR|G|dR> (the Appendix), and the rotated basis has e = diag(G)."""
    res = analysed(comm, packs[name], CUTS["one"])
    cs = res.cs
    V = gathered(comm, res.V)
    G = np.repeat(sm.modulation(cs.gathered().pos, cs.L, cs.planes) ** 2, cs.d)
    A = V.T @ (G[:, None] * V)
    assert np.allclose(A, np.diag(res.e), atol=1e-12)
    for e0, frac in res.fractions:
        assert ref.peel_extended(A, e0) == round(frac * cs.q)
    assert np.all(np.diff(res.fractions[:, 1]) <= 0)


# --------------------------------------------------------------------------- trial modes

@pytest.mark.parametrize("cut", ["one", "two axes"])
@pytest.mark.parametrize("name", ISO)
def test_trial_modes_obey_the_bound_and_the_variational_count(comm, packs, name, cut):
    """Eq. (rr) modes are orthonormal; each energy is below kappa z_max |grad g|^2 / e_b and,
    with e_b > e0, below omega_L^2 of Eq. (kkk); the true relaxed spectrum of the uncut packing
    (independent reference) interlaces with the trial modes' projected matrix and has at least
    q'/2 modes below sqrt(2) omega_t (counted here by MUMPS inertia)."""
    res = analysed(comm, packs[name], CUTS[cut])
    cs = res.cs
    ext = res.e > res.e0
    assert res.q_prime == ext.sum() > 0
    bound = cs.kappa * cs.z_max * res.grad2 / res.e[ext]
    assert np.all(res.trial_energy[ext] <= bound) and np.all(bound <= res.omega_L2 + 1e-12)
    assert cs.kappa <= 1.0  # harmonic contacts: k r^2 = (r/sigma)^2 < 1
    g = sm.modulation(cs.pos, cs.L, cs.planes)
    T = sm.trial_modes(res.V[:, ext], g, res.e[ext])
    assert sm.orthonormality_error(comm, T) < 1e-10
    Mu = sm.relaxed_matrix(comm, cs, cs.contacts)
    E, P = sm.energies(comm, Mu, T, projected=True)
    Mu.destroy()
    assert np.allclose(E, res.trial_energy[ext], rtol=1e-10, atol=1e-14)
    lam = np.load(os.path.join(DATA, name.replace(".h5", ".spectrum.npz")))["relaxed"]
    mu = np.linalg.eigvalsh(P)
    assert np.all(lam[:len(mu)] <= mu + 1e-10)  # Courant-Fischer / Cauchy interlacing
    assert res.n_below == np.count_nonzero(lam <= 2 * res.omega_t2)
    assert res.n_below >= res.q_prime / 2 and res.summary()["variational_ok"]


SIZES = {
    "2D, plane x = L/2": (sorted(glob.glob(os.path.join(DATA, "soft_d2_N*_m*.h5"))),
                          [sm.Plane(0, 0.5)], 0.1, 3.5),
    "3D, cube (--subdivide 1)": ([os.path.join(DATA, ISO[0])]
                                 + sorted(glob.glob(os.path.join(DATA, "soft_d3_N*_m*.h5"))),
                                 sm.subdivision_planes(1, 3), 0.05, 1.5),
}


@pytest.mark.parametrize("case", sorted(SIZES))
def test_trial_energies_decrease_like_one_over_L_squared(case):
    """2D bidisperse packings N = 64..1024 (L = 9..38) cut at x = L/2, and 3D packings
    N = 128..512 (L = 4.7..7.5) with all boundary contacts of the box cut, two members per size.

    Every soft mode's modulated energy <g dR|M|g dR> is below kappa z_max |grad g|^2 and their
    mean (basis independent) falls as L^-2; the orthonormalised trial modes with e > e0 stay
    below omega_L^2 and their mean energy omega_t^2 falls at least as L^-1.2 (in 2D it also
    carries the slow decrease of the extended fraction q'/q at these sizes, see
    docs/explanation/algorithms.md).  Without the sine modulation vanishing on the planes the cut contacts
    would add an L-independent energy and both slopes would be near 0 or -1.

    Physics over many packings: each rank runs it on COMM_SELF (the distributed path is
    covered by the other tests, which compare 1 and 2 ranks).
    """
    comm = PETSc.COMM_SELF
    files, cuts, e0, span = SIZES[case]
    Ls, Eg, Et = [], [], []
    for path in files:
        pack = h5md.read_packing(path)
        cs = sm.prepare(pack, cuts, allow_hyperstatic=True)
        res = sm.analyze(comm, cs, e0=e0)
        ext = res.e > res.e0
        assert np.all(res.modulated_energy <= cs.kappa * cs.z_max * res.grad2)
        assert np.all(res.trial_energy[ext] <= res.omega_L2)
        Ls.append(pack.L)
        Eg.append(np.mean(res.modulated_energy))
        Et.append(res.omega_t2)
    assert len(Ls) >= 5 and max(Ls) / min(Ls) > span
    slope_g = np.polyfit(np.log(Ls), np.log(Eg), 1)[0]
    slope_t = np.polyfit(np.log(Ls), np.log(Et), 1)[0]
    assert -2.3 < slope_g < -1.7, slope_g
    assert -2.5 < slope_t < -1.2, slope_t


# --------------------------------------------------------------------------- basis methods

@pytest.mark.parametrize("cut", ["one", "sub-boxes"])
@pytest.mark.parametrize("name", ISO)
def test_block_and_krylov_bases_agree(comm, packs, name, cut):
    """Block inverse iteration and SLEPc Krylov-Schur span the same null space (principal
    cosines 1), satisfy Eq. 3 to round-off, and find the same gap above it."""
    cs = sm.prepare(packs[name], planes(packs[name], CUTS[cut]), comm=comm)
    M = sm.relaxed_matrix(comm, cs, cs.kept)
    scale = cs.scale
    n_soft = sm.null_count(comm, M, scale) - cs.d
    a = sm.null_basis(comm, M, cs.d, n_soft, scale, "block")
    b = sm.null_basis(comm, M, cs.d, n_soft, scale, "krylov")
    S = sm.rigidity_matrix(comm, cs, cs.kept)
    for nb in (a, b):
        assert nb.V.shape[1] == n_soft
        assert sm.eq3_residual(comm, S, nb.V) < 1e-12
        assert sm.orthonormality_error(comm, nb.V) < 1e-12
        assert np.abs(nb.rayleigh).max() < 1e-12 * scale
    cos = np.linalg.svd(sm.gram(comm, a.V, b.V), compute_uv=False)
    assert np.allclose(cos, 1.0, atol=1e-9)
    assert a.gap == pytest.approx(b.gap, rel=1e-6) and a.gap > 1e-6 * scale
    S.destroy()
    M.destroy()


def test_block_start_does_not_depend_on_the_rank_layout():
    """The random start is drawn in fixed row blocks: any split of the rows gives the same
    global matrix."""
    whole = sm.random_block(0, 10000, 5, seed=3)
    parts = np.concatenate([sm.random_block(a, z, 5, seed=3)
                            for a, z in [(0, 2999), (2999, 3072), (3072, 7001), (7001, 10000)]])
    assert np.array_equal(whole, parts)


def test_unknown_basis_method_is_rejected(comm, packs):
    with pytest.raises(ParjamError, match="unknown basis method"):
        sm.null_basis(comm, None, 3, 1, 1.0, "lanczos")


# --------------------------------------------------------------------------- ranks

def test_one_rank_and_all_ranks_agree(comm, packs):
    """Basis-independent results (count, e spectrum, f, trial energies) on COMM_SELF and on
    COMM_WORLD (2 ranks under mpirun)."""
    pack = packs[ISO[0]]
    a = analysed(PETSc.COMM_SELF, pack, CUTS["two axes"])
    b = analysed(comm, pack, CUTS["two axes"])
    assert a.count == b.count and a.q_prime == b.q_prime and a.n_below == b.n_below
    assert np.allclose(a.e, b.e, atol=1e-11)
    assert np.allclose(a.overlap, b.overlap, atol=1e-11)
    assert np.allclose(a.trial_energy, b.trial_energy, rtol=1e-8, equal_nan=True)


# --------------------------------------------------------------------------- command line

def run_cli(argv):
    return cli.main(list(argv))


def test_cli_writes_the_issue_layout(comm, tmpdir_all):
    name = ISO[1]
    out = os.path.join(tmpdir_all, "soft.h5")
    src = os.path.join(DATA, name)
    assert run_cli(["softmodes", src, "--cut", "x=0.5", "--vectors", "-q", "--out", out]) == 0
    comm.tompi4py().Barrier()
    import h5py

    pack = h5md.read_packing(src)
    with h5py.File(out, "r") as f:
        g = f["softmodes"]
        assert int(g["count"][()]) == REF[name]["cut_plane_x_half"]["n_zero"]
        assert g["count"].attrs["trivial"] == 2 and g["count"].attrs["q"] == 12
        cut = g["cut_contacts"][()]
        basis = g["basis"][()]
        ov = g["overlap"][()]
        assert len(g["extension"]) == len(g["trial_energy"]) == basis.shape[0] == 11
        assert "input_sha256" in f["h5md/modules/parjam"].attrs
    assert cut.shape == (12, 2)
    assert np.sum(ov[:, 1]) / len(ov) == pytest.approx(1.0, abs=1e-12)
    net = network.analyze(pack)
    assert np.abs(basis[:, net.rattler]).max() == 0.0
    # Eq. 3 on the remaining contacts, in the packing's own indexing
    c = net.contacts
    kept = ~np.isin(c.i * pack.n + c.j, cut[:, 0] * pack.n + cut[:, 1])
    assert kept.sum() == len(c) - 12
    n = c.rij[kept] / c.r[kept, None]
    dR = basis[:, c.j[kept]] - basis[:, c.i[kept]]
    assert np.abs(np.einsum("mkd,kd->mk", dR, n)).max() < 1e-12


def test_cli_without_vectors_stores_no_basis(comm, tmpdir_all):
    out = os.path.join(tmpdir_all, "nobasis.h5")
    src = os.path.join(DATA, ISO[0])
    assert run_cli(["softmodes", src, "--subdivide", "2", "-q", "--out", out]) == 0
    comm.tompi4py().Barrier()
    import h5py

    with h5py.File(out, "r") as f:
        assert "basis" not in f["softmodes"]
        assert len(f["softmodes"].attrs["planes"]) == 6


def flower_packing(path):
    """Seven overlapping disks (a hexagonal flower) alone in a big box: every particle has at
    least 3 contacts, but no contact reaches the plane x = 0.1 L."""
    from parjam.net.system import Packing

    L = 20.0
    ang = np.arange(6) * np.pi / 3
    pos = np.vstack([[0.0, 0.0], 0.98 * np.stack([np.cos(ang), np.sin(ang)], axis=1)]) + L / 2
    pack = Packing(pos, np.ones(7), L)
    h5md.write_packing(path, pack, network.analyze(pack), {})


@pytest.mark.parametrize("case", ["hyperstatic", "cuts nothing", "no cut", "bad plane",
                                  "bad e0", "all rattlers"])
def test_cli_bad_input_gives_one_line_and_no_file(comm, tmpdir_all, capsys, case):
    out = os.path.join(tmpdir_all, f"bad-{case.replace(' ', '-')}.h5")
    src = os.path.join(DATA, HYPER[0])
    flower = os.path.join(tmpdir_all, "flower.h5")
    if comm.getRank() == 0 and not os.path.exists(flower):
        flower_packing(flower)
    comm.tompi4py().Barrier()
    argv, expect = {
        "hyperstatic": ([src, "--cut", "x=0.5"], "not isostatic"),
        "cuts nothing": ([flower, "--cut", "x=0.1", "--allow-hyperstatic"], "cuts no contact"),
        "no cut": ([src], "no cut given"),
        "bad plane": ([src, "--cut", "x=1.5"], "[0, 1)"),
        "bad e0": ([src, "--cut", "x=0.5", "--e0", "2"], "--e0"),
        "all rattlers": ([flower, "--cut", "x=0.5"], None),
    }[case]
    if case == "all rattlers":  # spread the flower apart: no contact left at all
        argv = [os.path.join(tmpdir_all, "apart.h5"), "--cut", "x=0.5"]
        if comm.getRank() == 0:
            from parjam.net.system import Packing

            p = Packing(np.array([[1.0, 1.0], [5.0, 5.0], [9.0, 2.0]]), np.ones(3), 12.0)
            h5md.write_packing(argv[0], p, network.analyze(p), {})
        comm.tompi4py().Barrier()
        expect = "all 3 particles are rattlers"
    capsys.readouterr()
    code = run_cli(["softmodes"] + argv + ["-q", "--out", out])
    err = capsys.readouterr().err
    assert code == 2
    assert not os.path.exists(out)
    if comm.getRank() == 0:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("parjam: error:") and expect in lines[0]


# --------------------------------------------------------------------------- figures

def test_figures_segment_cut_count_and_files(comm, packs, tmpdir_all):
    """Fig. "softfig" cuts only ncut contacts along the line: the null space is d + ncut - 1
    (the dense SVD agrees); both PNGs are written (rank 0)."""
    from parjam.plot import softmodes as psm

    pack = packs[ISO[1]]
    cs = psm.segment_cut(sm.prepare(pack, [sm.Plane(0, 0.5)]), sm.Plane(0, 0.5), 5)
    assert cs.q == 5 and cs.is_cut.sum() == 10  # both half-edges of each cut contact
    w = cs.gathered()
    assert ref.dense_null_space(ref.dense_rigidity(w, w.kept))[0] == cs.d + 4
    if comm.getRank() == 0:
        out = os.path.join(tmpdir_all, "softfig.png")
        info = psm.softfig(pack, out, ncut=5)
        assert info["count"] == cs.d + 4 and 0.0 < info["extension"] < 1.0
        psm.figs(pack, os.path.join(tmpdir_all, "figs.png"))
        assert os.path.getsize(out) > 1000
        assert os.path.getsize(os.path.join(tmpdir_all, "figs.png")) > 1000
